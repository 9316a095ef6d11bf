"""`mode=export checkpoint=<run dir or file>`: the policy as ONNX plus what a robot needs to run it.

Writes into the run directory:
  policy.onnx   observation [batch, Da] -> action [batch, J]; the running observation
                normalisation is inside the graph, the output is the Gaussian's mean
  policy.json   joint order, nominal pose, action scale (setpoint = nominal +
                action_scale · action), PD gains and torque limits, rates, and the
                layout of the observation vector; `fall_detector`: the fall detector's settings
                (`detector.*`) and the kinematic model it needs (fallkit.robots.kinematics);
                `sensitivity` (policies trained with env.sensitivity_inputs): the components
                whose weights the policy takes as inputs, their defaults and trained range
  end_poses.json  the robot's shipped artist poses, settled as training's are:
                name -> joints by name [rad] and root_quat (w, x, y, z); only for robots
                that ship artist poses
`fallkit.deploy.FallController.load(<run dir>)` runs them on a robot (docs/deploy.md).
The export is checked: onnxruntime must reproduce the torch policy's actions.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from fallkit.config import FallkitConfig
from fallkit.env.observations import MIN_SENSITIVITY, describe_actor_observation
from fallkit.errors import ConfigError
from fallkit.rl.policy import load_policy
from fallkit.robots.kinematics import exported_detector


def run_export(config: FallkitConfig, run_dir: Path) -> Path:
    if config.checkpoint is None:
        raise ConfigError("checkpoint: mode=export needs checkpoint=<run dir or checkpoint file>")
    policy = load_policy(config.checkpoint)
    spec, tcfg = policy.spec, policy.config
    net = policy.module.module  # float32, as load_policy builds it whatever train.precision was
    obs_dim = net.net.norm.mean.shape[0]
    onnx_path = run_dir / "policy.onnx"
    example = torch.zeros(1, obs_dim)
    # The TorchScript exporter (dynamo=False): the newer torch.export one needs onnxscript,
    # which fallkit does not depend on; this small MLP exports the same either way.
    torch.onnx.export(
        net, (example,), str(onnx_path), input_names=["observation"], output_names=["action"],
        dynamic_axes={"observation": {0: "batch"}, "action": {0: "batch"}}, dynamo=False,
    )  # fmt: skip
    _check_onnx(onnx_path, net, obs_dim)

    meta = {
        "robot": spec.name,
        "model_hash": spec.model_hash(),
        "checkpoint": str(policy.path.resolve()),  # where the policy came from, whatever the export's cwd
        "iteration": policy.iteration,
        "policy_hz": spec.policy_hz,
        "physics_timestep": spec.timestep,
        "joint_names": spec.joint_names,
        "nominal_pose": dict(zip(spec.joint_names, spec.nominal_q().tolist())),
        "action_scale": tcfg.env.action_scale,
        "trained_precision": tcfg.train.precision,  # the policy and this export compute in float32 (train.precision)
        "setpoint": "nominal_pose + action_scale * action"
        + (", clipped to the joint limits" if tcfg.env.clip_setpoints else ""),
        "clip_setpoints": tcfg.env.clip_setpoints,
        "base_body": spec.root_body,
        "joint_limits": dict(zip(spec.joint_names, spec.joint_limits.tolist())),
        "pd_gains": {j.name: {"kp": j.kp, "kd": j.kd, "torque_limit": j.torque_limit} for j in spec.joints},
        "observation_size": obs_dim,
        "observation_layout": describe_actor_observation(
            spec, tcfg.env.sensitivity_inputs.enabled, tcfg.env.observe_gravity
        ),
        "observe_gravity": tcfg.env.observe_gravity,  # 'gravity', 'goal_gravity' in the layout (env.observe_gravity)
        "fall_detector": exported_detector(spec, config.detector),  # fallkit.deploy.FallDetector.load reads it
        "tracking_blend": {
            "observed": tcfg.env.observe_blend,
            "blend_time": tcfg.reward.blend_time,
            "formula": "x = clamp(t / blend_time, 0, 1); u = x*x*(3 - 2*x), t = seconds since the fall began "
            "(0 at the first step); observation 'blend' = u if observed else 0",
        },
    }
    if tcfg.env.sensitivity_inputs.enabled:
        meta["sensitivity"] = _sensitivity_inputs(spec, tcfg)
    (run_dir / "policy.json").write_text(json.dumps(meta, indent=2))
    poses = _write_end_poses(spec, run_dir / "end_poses.json")
    print(f"exported {onnx_path} and {run_dir / 'policy.json'} (iteration {policy.iteration} of {policy.path})"
          + (f", {poses} end poses in {run_dir / 'end_poses.json'}" if poses else ""))  # fmt: skip
    return onnx_path


def _sensitivity_inputs(spec, config: FallkitConfig) -> dict:
    """The sensitivity inputs of a policy trained with env.sensitivity_inputs: components, their defaults
    (the training robot's weights), the range the policy saw, and how the weights become inputs."""
    r = config.env.sensitivity_inputs
    drawn, defaults = r.components or spec.component_names, dict(zip(spec.component_names, spec.sensitivity.tolist()))
    how = {"each": "every component per episode",
           "one": "one component per episode, the others at their defaults"}[r.draw]  # fmt: skip
    if r.components is not None:
        how += f"; only {r.components} drawn, the others fixed at their defaults"
    return {
        "components": spec.component_names,
        "defaults": defaults,
        "trained_range": {c: [w * r.low, w * r.high] if c in drawn else [w, w] for c, w in defaults.items()},
        "trained_draw": how,
        "formula": f"observation 'sensitivity' = ln(max(w_c, {MIN_SENSITIVITY:g})) per component, in this order",
    }


def _write_end_poses(spec, path: Path) -> int:
    """The robot's shipped artist poses, settled (what env.poses=artist trains and evaluates toward)."""
    from fallkit.poses.artist import read_artist_poses, settle_artist_poses, shipped_artist_file

    source = shipped_artist_file(spec)
    if source is None:
        return 0
    settled, _ = settle_artist_poses(source, spec, read_artist_poses(source, spec))
    poses = {
        name: {"joints": dict(zip(spec.joint_names, q.tolist())), "root_quat": quat.tolist()}
        for name, q, quat in zip(settled.names, settled.joint_pos.double(), settled.root_quat.double())
    }
    path.write_text(json.dumps(poses, indent=2))
    return len(poses)


def _check_onnx(path: Path, net: torch.nn.Module, obs_dim: int) -> None:
    import onnxruntime

    obs = torch.randn(8, obs_dim, generator=torch.Generator().manual_seed(0)) * 3.0
    prior = net.net.prior
    if prior is not None and prior.blend_columns.numel():  # u(t) lives in [0, 1]: beyond it u^8 of a random
        obs[:, prior.blend_columns] = obs[:, prior.blend_columns].sigmoid()  # draw (~6^8) swamps float32 rounding
    with torch.no_grad():
        want = net(obs).numpy()
    got = onnxruntime.InferenceSession(str(path)).run(["action"], {"observation": obs.numpy()})[0]
    if not np.allclose(got, want, atol=1e-4, rtol=1e-4):
        raise RuntimeError(f"ONNX export of {path} does not reproduce the policy (max error {np.abs(got - want).max():.2e})")

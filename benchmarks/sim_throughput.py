"""Physics throughput of fallkit's batch simulators against the raw engines.

Both sides start from the same initial falling states (paper Table II), hold
the same joint setpoints and run the same number of physics steps on the same
model and hardware, so the robots fall and then lie in contact:

  mujoco backend (CPU threads)
    fallkit  MujocoSim.step: PD control, per-substep contact force per component,
             instability checks, torch state tensors
    raw      mujoco.batch.Batch.step(nstep=substeps): mj_step on the thread pool,
             no recording, no outputs (the physics limit of the machine)
  warp backend (GPU, or Warp's CPU device)
    fallkit  WarpSim.step: the same outputs, plus the overflow check (one 8-byte
             device-to-host read per policy step)
    raw      mujoco_warp.step x substeps on the same model and device, captured as
             one graph and replayed, no outputs (the physics limit of the device)

Prints one JSON object on its last line: `ratio` = fallkit / raw for the mujoco
backend (target >= 0.9), `warp_ratio` for the warp backend at its largest world
count (target >= 0.85 at 4096 worlds on a GPU), and every measurement under `runs`.

    python benchmarks/sim_throughput.py [--backend mujoco|warp|both] [--worlds 256 1024]
        [--steps 150] [--warp-steps N] [--threads 0] [--device auto] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import mujoco
import mujoco.batch
import numpy as np
import torch

from fallkit.api import get_robot
from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.sim import make_sim


def time_fallkit(spec, qpos, qvel, targets, steps: int, threads: int) -> float:
    sim = make_sim(spec, len(qpos), "mujoco", threads=threads)
    sim.reset(torch.arange(len(qpos)), qpos, qvel)
    t = torch.as_tensor(targets, dtype=torch.float32)
    sim.step(t)  # warm-up (first call allocates)
    sim.reset(torch.arange(len(qpos)), qpos, qvel)
    start = time.perf_counter()
    for _ in range(steps):
        sim.step(t)
    return time.perf_counter() - start


def time_raw(spec, qpos, qvel, targets, steps: int, threads: int) -> float:
    model = spec.mj_model()
    batch = mujoco.batch.Batch(model, len(qpos), nthread=threads)

    def reset() -> None:
        batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
        batch.bind("qpos")[:] = qpos.numpy()
        batch.bind("qvel")[:] = qvel.numpy()
        batch.bind("ctrl")[:] = targets
        batch.forward()

    reset()
    batch.step(nstep=spec.substeps)
    reset()
    start = time.perf_counter()
    for _ in range(steps):
        batch.step(nstep=spec.substeps)
    return time.perf_counter() - start


class WarpRaw:
    """Raw mujoco_warp on the same model and device: `substeps` x `mjw.step`, one graph."""

    def __init__(self, spec, num_worlds: int, device: str):
        from fallkit.sim.warp_setup import default_buffers, init_warp, put_warp_model, use_graphs

        wp = init_warp()
        import mujoco_warp as mjw

        self.wp, self.mjw, self.substeps = wp, mjw, spec.substeps
        self.device = wp.get_device(device)
        model = spec.mj_model()
        nconmax, njmax = default_buffers(model)
        with wp.ScopedDevice(self.device):
            self.m = put_warp_model(model, num_worlds, per_world_gains=False)
            self.d = mjw.put_data(model, mujoco.MjData(model), nworld=num_worlds, nconmax=nconmax, njmax=njmax)
            self._run()  # load every kernel before capture
            self.graph = None
            if use_graphs(self.device):
                with wp.ScopedCapture(device=self.device) as cap:
                    self._run()
                self.graph = cap.graph

    def _run(self) -> None:
        for _ in range(self.substeps):
            self.mjw.step(self.m, self.d)

    def reset(self, qpos, qvel, targets) -> None:
        wp, d = self.wp, self.d
        with wp.ScopedDevice(self.device):
            self.mjw.reset_data(self.m, d)
            wp.to_torch(d.qpos).copy_(qpos)
            wp.to_torch(d.qvel).copy_(qvel)
            wp.to_torch(d.ctrl).copy_(targets)
            wp.synchronize_device(self.device)

    def policy_step(self) -> None:
        with self.wp.ScopedDevice(self.device):
            if self.graph is not None:
                self.wp.capture_launch(self.graph)
            else:
                self._run()


def bench_mujoco(spec, worlds: int, steps: int, threads: int, repeats: int) -> dict:
    qpos, qvel = InitialStateSampler(spec).sample(worlds, torch.Generator().manual_seed(0))
    targets = np.tile(spec.nominal_q(), (worlds, 1))
    physics_steps = worlds * steps * spec.substeps
    # Interleave the two so that machine noise (about ±10 % between identical runs
    # on a shared 2-core machine) hits both alike; the ratio is the median of the
    # per-pair ratios, the absolute figures the median of each side.
    fk, raw = [], []
    for _ in range(repeats):
        fk.append(time_fallkit(spec, qpos, qvel, targets, steps, threads))
        raw.append(time_raw(spec, qpos, qvel, targets, steps, threads))
    return {
        "backend": "mujoco",
        "worlds": worlds,
        "threads": threads or os.cpu_count(),
        "raw_steps_per_s": round(physics_steps / float(np.median(raw))),
        "fallkit_steps_per_s": round(physics_steps / float(np.median(fk))),
        "ratio": round(float(np.median(np.array(raw) / np.array(fk))), 4),
    }


def bench_warp(spec, worlds: int, steps: int, device: str, repeats: int) -> dict:
    from fallkit.sim.warp_setup import resolve_device

    device = resolve_device(device)
    qpos, qvel = InitialStateSampler(spec).sample(worlds, torch.Generator().manual_seed(0))
    targets = torch.tensor(np.tile(spec.nominal_q(), (worlds, 1)), dtype=torch.float32, device=device)
    q32, v32 = qpos.float().to(device), qvel.float().to(device)
    sim = make_sim(spec, worlds, "warp", device=device)
    raw = WarpRaw(spec, worlds, device)
    ids = torch.arange(worlds, device=device)
    physics_steps = worlds * steps * spec.substeps

    def sync() -> None:
        if device.startswith("cuda"):
            torch.cuda.synchronize(device)

    def time_fk() -> float:
        sim.reset(ids, q32, v32)
        sync()
        start = time.perf_counter()
        for _ in range(steps):
            sim.step(targets)
        sync()
        return time.perf_counter() - start

    def time_raw_warp() -> float:
        raw.reset(q32, v32, targets)
        start = time.perf_counter()
        for _ in range(steps):
            raw.policy_step()
        raw.wp.synchronize_device(raw.device)
        return time.perf_counter() - start

    fk, rw = [], []
    for _ in range(repeats):
        fk.append(time_fk())
        rw.append(time_raw_warp())
    return {
        "backend": "warp",
        "worlds": worlds,
        "device": device,
        "graphs": raw.graph is not None,
        "raw_steps_per_s": round(physics_steps / float(np.median(rw))),
        "fallkit_steps_per_s": round(physics_steps / float(np.median(fk))),
        "ratio": round(float(np.median(np.array(rw) / np.array(fk))), 4),
        "unstable": sim.num_unstable,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robot", default="biped20")
    p.add_argument("--backend", choices=("mujoco", "warp", "both"), default="mujoco")
    p.add_argument("--worlds", type=int, nargs="+", default=[256], help="one or more world counts")
    p.add_argument("--steps", type=int, default=150, help="policy steps (150 = 3 s: fall, then lie)")
    p.add_argument("--warp-steps", type=int, default=None, help="policy steps for warp (default: --steps)")
    p.add_argument("--threads", type=int, default=0, help="mujoco: 0 = all cores")
    p.add_argument("--device", default="auto", help="warp: auto | cpu | cuda:N")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(1)  # the physics threads are MuJoCo's

    spec = get_robot(args.robot)
    runs: list[dict] = []
    for worlds in args.worlds:
        if args.backend in ("mujoco", "both"):
            r = bench_mujoco(spec, worlds, args.steps, args.threads, args.repeats)
            runs.append(r)
            print(f"mujoco  {worlds:6d} worlds x {args.steps} policy steps x {spec.substeps} substeps, {r['threads']} threads: "
                  f"raw {r['raw_steps_per_s']:10d}  fallkit {r['fallkit_steps_per_s']:10d} physics steps/s  "
                  f"ratio {r['ratio']:.3f} (target >= 0.90)", flush=True)
        if args.backend in ("warp", "both"):
            steps = args.warp_steps or args.steps
            r = bench_warp(spec, worlds, steps, args.device, args.repeats)
            runs.append(r)
            print(f"warp    {worlds:6d} worlds x {steps} policy steps x {spec.substeps} substeps, {r['device']}: "
                  f"raw {r['raw_steps_per_s']:10d}  fallkit {r['fallkit_steps_per_s']:10d} physics steps/s  "
                  f"ratio {r['ratio']:.3f} (target >= 0.85 at 4096 worlds on a GPU)", flush=True)
    print(f"(medians of {args.repeats} interleaved fallkit/raw pairs; robot {args.robot})")

    mj = [r for r in runs if r["backend"] == "mujoco"]
    summary: dict = {"backend": "mujoco" if mj else "warp", "robot": args.robot}
    if mj:  # the foundation benchmark's keys, from the last mujoco world count
        last = mj[-1]
        summary.update(worlds=last["worlds"], threads=last["threads"],
                       raw_steps_per_s=last["raw_steps_per_s"], fallkit_steps_per_s=last["fallkit_steps_per_s"],
                       ratio=last["ratio"])  # fmt: skip
    wa = [r for r in runs if r["backend"] == "warp"]
    if wa:
        top = max(wa, key=lambda r: r["worlds"])
        summary.update(warp_worlds=top["worlds"], warp_device=top["device"], warp_raw_steps_per_s=top["raw_steps_per_s"],
                       warp_fallkit_steps_per_s=top["fallkit_steps_per_s"], warp_ratio=top["ratio"])  # fmt: skip
    if len(runs) > 1:
        summary["runs"] = runs
    print(json.dumps(summary))


if __name__ == "__main__":
    main()

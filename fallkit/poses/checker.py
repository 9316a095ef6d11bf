"""Pose queries shared by the samplers: self-collision and the lowest point.

`PoseChecker` runs MuJoCo's own collision detection on many candidate poses at
once (a `mujoco.batch.Batch`, all threads), with the robot lifted far above the
floor so that every contact it finds is a self-contact.  It also reports how far
the lowest collision geom reaches below the root, so a pose can be placed to
just clear the ground.
"""

from __future__ import annotations

import mujoco
import mujoco.batch
import numpy as np
import torch

from fallkit.errors import RobotSpecError
from fallkit.machine import core_share
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import Layout

_LIFT = 10.0  # [m] far above the floor: only self-contacts remain


class PoseChecker:
    def __init__(self, spec: RobotSpec, chunk: int = 512, threads: int = 0):
        self.spec = spec
        self.model = spec.mj_model()
        self.layout = Layout(spec)
        self.chunk = chunk
        self.batch = mujoco.batch.Batch(self.model, chunk, nthread=threads or core_share())
        self._qpos = self.batch.bind("qpos")
        self._ncon = self.batch.bind("ncon")
        self._gpos = self.batch.bind("geom_xpos")
        self._gmat = self.batch.bind("geom_xmat")
        m = self.model
        floor = m.geom("floor").id
        collides = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
        self._geoms = np.flatnonzero(collides & (np.arange(m.ngeom) != floor))
        self._type = m.geom_type[self._geoms]
        self._size = m.geom_size[self._geoms]
        self._aabb = m.geom_aabb[self._geoms]  # local centre (3) and half sizes (3)

    def check(self, qpos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For MuJoCo-layout poses [k, nq]: (self-colliding [k] bool, lowest point [k] relative to root z)."""
        q = np.asarray(qpos.detach().cpu(), dtype=np.float64)
        k = len(q)
        colliding = np.zeros(k, bool)
        lowest = np.zeros(k)
        rz = self.layout.root_qpos + 2
        for start in range(0, k, self.chunk):
            part = q[start : start + self.chunk]
            n = len(part)
            ids = np.arange(n)
            self._qpos[:n] = part
            self._qpos[:n, rz] = _LIFT
            self.batch.forward(ids, stage=mujoco.mjtStage.mjSTAGE_POS)
            colliding[start : start + n] = self._ncon[:n] > 0
            lowest[start : start + n] = self._lowest(n) - _LIFT
        return torch.from_numpy(colliding), torch.from_numpy(lowest)

    def _lowest(self, n: int) -> np.ndarray:
        """Lowest z of any collision geom, exact for spheres, capsules and boxes, AABB otherwise."""
        pos = self._gpos[:n, self._geoms]  # [n, g, 3]
        rz = self._gmat[:n, self._geoms].reshape(n, -1, 3, 3)[:, :, 2, :]  # third row: z of local axes
        size, typ = self._size, self._type
        z = pos[..., 2] + np.einsum("ngk,gk->ng", rz, self._aabb[:, :3]) - np.einsum(
            "ngk,gk->ng", np.abs(rz), self._aabb[:, 3:]
        )
        sphere = typ == mujoco.mjtGeom.mjGEOM_SPHERE
        z[:, sphere] = pos[:, sphere, 2] - size[sphere, 0]
        capsule = typ == mujoco.mjtGeom.mjGEOM_CAPSULE
        z[:, capsule] = pos[:, capsule, 2] - np.abs(rz[:, capsule, 2]) * size[capsule, 1] - size[capsule, 0]
        box = typ == mujoco.mjtGeom.mjGEOM_BOX
        z[:, box] = pos[:, box, 2] - np.einsum("ngk,gk->ng", np.abs(rz[:, box]), size[box])
        return z.min(axis=1)

    def place_on_ground(self, qpos: torch.Tensor, clearance: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Set root height so the lowest geom is `clearance` above the floor; also return self-collision."""
        colliding, lowest = self.check(qpos)
        out = qpos.clone()
        rz = self.layout.root_qpos + 2
        out[:, rz] = clearance - lowest.to(out.dtype)
        return out, colliding

    def on_ground(
        self,
        root_quat: torch.Tensor | np.ndarray,
        joint_pos: torch.Tensor | np.ndarray,
        clearance: float = 0.0,
        root_pos: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Poses [k] as MuJoCo qpos [k, nq] (float64), lowest geom `clearance` above the floor; and self-collision [k].

        root_quat [k, 4] and joint_pos [k, J] (policy order); root_pos [k, 3] gives the
        root's x and y (default 0), its z is replaced by the height that places the pose.
        """
        quat = torch.as_tensor(root_quat, dtype=torch.float64)
        joints = torch.as_tensor(joint_pos, dtype=torch.float64)
        pos = torch.zeros(len(quat), 3, dtype=torch.float64) if root_pos is None else root_pos.to(torch.float64)
        return self.place_on_ground(self.layout.qpos(pos, quat, joints), clearance)

    def sample_joints(
        self, n: int, generator: torch.Generator, spread: float = 1.0, max_rounds: int = 200
    ) -> torch.Tensor:
        """n self-collision-free joint configurations [n, J], uniform within the limits.

        spread < 1 draws from the limits shrunk toward the nominal pose by that
        factor (a curriculum knob); 1.0 is uniform over the full range.
        """
        lim = torch.as_tensor(self.spec.joint_limits, dtype=torch.float64)
        nominal = torch.as_tensor(self.spec.nominal_q(), dtype=torch.float64)
        lo = nominal + spread * (lim[:, 0] - nominal)
        hi = nominal + spread * (lim[:, 1] - nominal)
        ident = torch.tensor([[0.0, 0.0, _LIFT]], dtype=torch.float64)
        quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
        kept: list[torch.Tensor] = []
        have = 0
        for _ in range(max_rounds):
            m = max(2 * (n - have), 64)
            q = lo + (hi - lo) * torch.rand(m, len(lo), generator=generator, dtype=torch.float64)
            colliding, _ = self.check(self.layout.qpos(ident.expand(m, 3), quat.expand(m, 4), q))
            ok = q[~colliding]
            kept.append(ok)
            have += len(ok)
            if have >= n:
                return torch.cat(kept)[:n]
        raise RobotSpecError(
            f"robot '{self.spec.name}': found only {have} of {n} self-collision-free joint configurations "
            f"in {max_rounds} rounds; the joint limits or collision geometry make almost every pose self-collide"
        )

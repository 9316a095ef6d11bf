"""Which end pose a training episode falls toward.

The paper draws it uniformly from the training split, whatever the fall's initial state. With
`env.heading_end_poses = q`, a share q of the training episodes instead take, of
`env.heading_candidates` poses drawn uniformly, the one lying closest to where the fall is heading
(its capture point, `fallkit.pose_choice`): more training falls whose end pose lies the way they
fall. It was built because trained policies seemed to lose many of the falls the open-loop seek
lands right; measured, it kept no more of them and turned fewer of the others, and that split turned
out to select on seek's own outcome (docs/learning_log.md: "Training end poses paired with the way the
fall heads", "The easy falls, the other way round"). Off by default.

Only the training draw changes. Evaluation, render and sim2sim reset their worlds to given falls
and end poses (`FallEnv.reset_to`), so the task they measure is the paper's.
"""

from __future__ import annotations

import torch

from fallkit.pose_choice import ground_directions, predicted_ground
from fallkit.rotations import quat_rotate_inverse
from fallkit.sim.base import Layout


class EndPoseDraw:
    """End-pose ids for restarting worlds, given their initial states."""

    def __init__(self, root_quat: torch.Tensor, layout: Layout, share: float = 0.0, candidates: int = 8):
        """root_quat [P, 4]: the end poses'; layout: the simulator's (where the root sits in qpos and qvel)."""
        self.count, self.layout, self.share, self.candidates = root_quat.shape[0], layout, share, candidates
        # each pose's side facing the ground, in its root frame [P, 3]: what the capture point is compared with
        self.ground = torch.from_numpy(ground_directions(root_quat.detach().cpu().double().numpy())) if share else None

    def __call__(self, qpos: torch.Tensor, qvel: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """[n] ids for n worlds starting at MuJoCo-layout (qpos, qvel) [n, nq], [n, nv] (CPU, float64)."""
        n, device = qpos.shape[0], generator.device
        if self.share == 0:  # the paper's draw, the same numbers as before the option existed
            return torch.randint(self.count, (n,), generator=generator, device=device)
        drawn = torch.randint(self.count, (n, self.candidates), generator=generator, device=device)
        heading = torch.rand(n, generator=generator, device=device) < self.share
        r, v = self.layout.root_qpos, self.layout.root_qvel
        quat = qpos[:, r + 3 : r + 7]
        lin_vel = quat_rotate_inverse(quat, qvel[:, v : v + 3])  # the base frame, as an estimator gives it
        predicted = torch.from_numpy(predicted_ground(quat.numpy(), lin_vel.numpy()))  # [n, 3]
        cos = torch.einsum("nd,nkd->nk", predicted, self.ground[drawn.cpu()])
        closest = drawn.gather(1, cos.argmax(dim=1, keepdim=True).to(device)).view(-1)
        return torch.where(heading, closest, drawn[:, 0])

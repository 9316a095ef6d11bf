"""Left–right mirror augmentation of PPO's minibatches (train.ppo.mirror; rsl_rl's symmetry augmentation):
the mirror image of each sample, and how far the policy is from acting symmetrically."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from fallkit.env.mirror import ObservationMirror


def with_mirror_image(mirror: ObservationMirror, data: TensorDict, keys) -> TensorDict:
    """The minibatch followed by its mirror image (what the loss reads, nothing else; `keys`: the loss's
    tensor keys).

    The image keeps the original's advantage, value target, old value and old log-probability:
    the mirrored fall is as good as the fall, and its action is taken as having been as likely
    (exactly so for a symmetric collecting policy, its std included), as rsl_rl's symmetry augmentation does.
    """
    shared = [k for k in (keys.advantage, keys.value_target, keys.value, keys.sample_log_prob) if k in data.keys()]
    original = data.select("policy", "critic", keys.action, *shared)
    image = original.clone(recurse=False)
    image.set("policy", mirror.actor(original["policy"]))
    image.set("critic", mirror.critic(original["critic"]))
    image.set(keys.action, mirror.action(original[keys.action]))
    return torch.cat([original, image], dim=0)


def mirror_error(mirror: ObservationMirror, loc: torch.Tensor, mirrored_loc: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between π(mirror(o)) (`mirrored_loc`) and mirror(π(o)) (`loc` mirrored),
    the policy means [action units²].

    0 for a policy that acts on a mirrored fall exactly as the mirror image of how it acts on the
    fall; the augmentation should drive it down, and without it nothing does.
    """
    return (mirrored_loc - mirror.action(loc)).square().mean()

"""Quaternion helpers on batches (w, x, y, z), torch.

Small and explicit on purpose: the path frame, the end-pose goal and the
orientation metrics are all built from these few functions.
"""

from __future__ import annotations


import torch


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v by unit quaternions q (frame of q -> parent frame)."""
    w, xyz = q[..., :1], q[..., 1:]
    t = 2.0 * torch.cross(xyz, v, dim=-1)
    return v + w * t + torch.cross(xyz, t, dim=-1)


def quat_rotate_inverse(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v by q⁻¹ (parent frame -> frame of q)."""
    return quat_rotate(quat_conj(q), v)


def quat_from_axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    half = 0.5 * angle.unsqueeze(-1)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return torch.cat((torch.cos(half), torch.sin(half) * axis), dim=-1)


def quat_from_euler(roll: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """q = Rz(yaw) · Ry(pitch) · Rx(roll): roll applied first, then pitch, then yaw (extrinsic)."""
    def about(axis: int, angle: torch.Tensor) -> torch.Tensor:
        q = torch.zeros(*angle.shape, 4, dtype=angle.dtype, device=angle.device)
        q[..., 0] = torch.cos(0.5 * angle)
        q[..., 1 + axis] = torch.sin(0.5 * angle)
        return q

    return quat_mul(about(2, yaw), quat_mul(about(1, pitch), about(0, roll)))


def yaw_of(q: torch.Tensor) -> torch.Tensor:
    """Heading angle: direction of the body x-axis projected on the ground plane."""
    x = quat_rotate(q, torch.tensor([1.0, 0.0, 0.0], dtype=q.dtype, device=q.device).expand_as(q[..., 1:]))
    return torch.atan2(x[..., 1], x[..., 0])


def yaw_quat(q: torch.Tensor) -> torch.Tensor:
    """The pure rotation about world z by the heading of q (the path frame's orientation)."""
    yaw = yaw_of(q)
    zero = torch.zeros_like(yaw)
    return quat_from_euler(zero, zero, yaw)


def gravity_in_frame(q: torch.Tensor) -> torch.Tensor:
    """R(q)ᵀ e_z: the world up axis expressed in the frame of q (paper Table I, orientation term)."""
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=q.dtype, device=q.device).expand_as(q[..., 1:])
    return quat_rotate_inverse(q, ez)


def geodesic_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Rotation angle [rad] between orientations a and b, in [0, π]."""
    dot = (a * b).sum(-1).abs().clamp(max=1.0)
    return 2.0 * torch.acos(dot)


def normalize(q: torch.Tensor) -> torch.Tensor:
    return q / q.norm(dim=-1, keepdim=True)


__all__ = [
    "quat_mul", "quat_conj", "quat_rotate", "quat_rotate_inverse", "quat_from_axis_angle",
    "quat_from_euler", "yaw_of", "yaw_quat", "gravity_in_frame", "geodesic_angle", "normalize",
]  # fmt: skip

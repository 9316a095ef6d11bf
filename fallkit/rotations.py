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
    return _rotate(q[..., :1], q[..., 1:], v)


def _rotate(w: torch.Tensor, xyz: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """v rotated by the unit quaternion (w, xyz): v + 2w(xyz × v) + xyz × (2 xyz × v)."""
    t = 2.0 * torch.cross(xyz, v, dim=-1)
    return v + w * t + torch.cross(xyz, t, dim=-1)


def quat_rotate_inverse(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v by q⁻¹ (parent frame -> frame of q): quat_rotate with the vector part negated, written
    out so that no constant tensor is made per call (on a GPU: a host-to-device copy every env step)."""
    return _rotate(q[..., :1], -q[..., 1:], v)


def quat_from_euler(roll: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """q = Rz(yaw) · Ry(pitch) · Rx(roll): roll applied first, then pitch, then yaw (extrinsic)."""
    def about(axis: int, angle: torch.Tensor) -> torch.Tensor:
        q = torch.zeros(*angle.shape, 4, dtype=angle.dtype, device=angle.device)
        q[..., 0] = torch.cos(0.5 * angle)
        q[..., 1 + axis] = torch.sin(0.5 * angle)
        return q

    return quat_mul(about(2, yaw), quat_mul(about(1, pitch), about(0, roll)))


def heading_quat(q: torch.Tensor) -> torch.Tensor:
    """The rotation about world z in q's swing–twist decomposition q = heading ⊗ tilt.

    The path frame's orientation (paper Sec. IV-A). Unlike the heading of the body
    x-axis projected on the ground (singular at ±90° pitch: a robot lying on its back
    or front, the most common end poses), this is continuous everywhere except upside
    down (tilt 180°), where it falls back to the identity.
    """
    w, z = q[..., 0], q[..., 3]
    n = torch.sqrt(w * w + z * z)
    ok = n > 1e-6
    n = torch.where(ok, n, torch.ones_like(n))
    zero = torch.zeros_like(w)
    return torch.stack((torch.where(ok, w / n, torch.ones_like(w)), zero, zero, torch.where(ok, z / n, zero)), -1)


def tilt_quat(q: torch.Tensor) -> torch.Tensor:
    """heading_quat(q)⁻¹ ⊗ q: q expressed in its path frame, yaw-free, w ≥ 0, z = 0.

    Depends only on the direction of gravity in the frame of q, so it is the same
    for q and for any rotation of q about world z (and for -q).
    """
    # closed form of heading_quat(q)⁻¹ ⊗ q (the swing): (n, (wx + zy)/n, (wy − zx)/n, 0), n = |(w, z)|
    w, x, y, z = q.unbind(-1)
    n = torch.sqrt(w * w + z * z)
    ok = n > 1e-6
    inv = 1.0 / torch.where(ok, n, torch.ones_like(n))
    tx = torch.where(ok, (w * x + z * y) * inv, x)
    ty = torch.where(ok, (w * y - z * x) * inv, y)
    return torch.stack((n, tx, ty, torch.zeros_like(n)), -1)


def gravity_in_frame(q: torch.Tensor) -> torch.Tensor:
    """R(q)ᵀ e_z: the world up axis expressed in the frame of q (paper Table I, orientation term)."""
    # closed form (third row of R(q)): a handful of ops, it runs every policy step
    w, x, y, z = q.unbind(-1)
    return torch.stack((2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)), dim=-1)


def geodesic_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Rotation angle [rad] between orientations a and b, in [0, π]."""
    dot = (a * b).sum(-1).abs().clamp(max=1.0)
    return 2.0 * torch.acos(dot)


def normalize(q: torch.Tensor) -> torch.Tensor:
    return q / q.norm(dim=-1, keepdim=True)


def yaw_align(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a turned about the world z axis by the yaw that brings it closest to b (geodesically).

    With d = b ⊗ a⁻¹, ⟨Rz(ψ) ⊗ a, b⟩ = cos(ψ/2)·d_w + sin(ψ/2)·d_z, largest at
    ψ = 2·atan2(d_z, d_w). Needs no heading, so it is defined for every
    orientation (also lying face up). The paper's MROE compares b with this.
    """
    d = quat_mul(b, quat_conj(a))
    half = torch.atan2(d[..., 3], d[..., 0])
    z = torch.zeros_like(half)
    return quat_mul(torch.stack((torch.cos(half), z, z, torch.sin(half)), dim=-1), a)


__all__ = [
    "quat_mul", "quat_conj", "quat_rotate", "quat_rotate_inverse", "quat_from_euler", "heading_quat",
    "tilt_quat", "gravity_in_frame", "geodesic_angle", "normalize", "yaw_align",
]  # fmt: skip

"""Quaternion and rotation helpers, batched over any leading dimensions.

Quaternions are `(..., 4)` tensors ordered (w, x, y, z) with the Hamilton product, as in
the HumanML3D tools; `qrot(q, v)` rotates the vector v by q (active rotation). Rotation
matrices act on column vectors, so `quat_to_matrix(q) @ v == qrot(q, v)`.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "qmul", "qinv", "qnormalize", "qrot", "qbetween", "axis_angle_to_quat",
    "quat_to_matrix", "matrix_to_quat", "quat_to_cont6d", "cont6d_to_matrix", "cont6d_to_quat",
    "matrix_to_euler", "euler_to_matrix", "identity_quat",
]


def _check_last(x: Tensor, size: int, name: str) -> None:
    if x.shape[-1] != size:
        raise ValueError(f"{name} must have last dimension {size}, got shape {tuple(x.shape)}")


def identity_quat(*shape: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """(*shape, 4) identity quaternions."""
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def qmul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of (..., 4) quaternions (broadcasting)."""
    _check_last(a, 4, "qmul: a")
    _check_last(b, 4, "qmul: b")
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


def qinv(q: Tensor) -> Tensor:
    """Inverse of unit quaternions (the conjugate), (..., 4)."""
    _check_last(q, 4, "qinv: q")
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def qnormalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Scale (..., 4) quaternions to unit norm."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def qrot(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4) (broadcasting)."""
    _check_last(q, 4, "qrot: q")
    _check_last(v, 3, "qrot: v")
    shape = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    q = q.expand(*shape, 4)
    v = v.expand(*shape, 3)
    qvec = q[..., 1:]
    uv = torch.linalg.cross(qvec, v, dim=-1)
    uuv = torch.linalg.cross(qvec, uv, dim=-1)
    return v + 2.0 * (q[..., :1] * uv + uuv)


def qbetween(v0: Tensor, v1: Tensor) -> Tensor:
    """Shortest-arc unit quaternion rotating direction v0 onto v1, both (..., 3).

    Same formula as HumanML3D's `qbetween`; for opposite vectors (where that formula gives
    a zero quaternion) a half turn about an axis perpendicular to v0 is returned instead.
    """
    _check_last(v0, 3, "qbetween: v0")
    _check_last(v1, 3, "qbetween: v1")
    v0, v1 = torch.broadcast_tensors(v0, v1)
    v = torch.linalg.cross(v0, v1, dim=-1)
    w = torch.sqrt((v0**2).sum(-1, keepdim=True) * (v1**2).sum(-1, keepdim=True)) + (
        v0 * v1
    ).sum(-1, keepdim=True)
    q = torch.cat([w, v], dim=-1)
    norm = q.norm(dim=-1, keepdim=True)
    scale = torch.sqrt((v0**2).sum(-1, keepdim=True) * (v1**2).sum(-1, keepdim=True))
    # Rounding leaves |q| near sqrt(eps) of the scale for opposite vectors (about 1e-7 in
    # float32), so the test scales with the dtype.
    degenerate = norm <= torch.finfo(q.dtype).eps ** 0.5 * scale.clamp_min(1e-30)
    if bool(degenerate.any()):
        # Any axis perpendicular to v0: cross with x, or with y when v0 is along x.
        ex = torch.zeros_like(v0)
        ex[..., 0] = 1.0
        ey = torch.zeros_like(v0)
        ey[..., 1] = 1.0
        axis = torch.linalg.cross(v0, ex, dim=-1)
        use_y = axis.norm(dim=-1, keepdim=True) < 1e-6 * v0.norm(dim=-1, keepdim=True)
        axis = torch.where(use_y, torch.linalg.cross(v0, ey, dim=-1), axis)
        half_turn = torch.cat([torch.zeros_like(w), axis], dim=-1)
        q = torch.where(degenerate, half_turn, q)
    return qnormalize(q)


def axis_angle_to_quat(axis_angle: Tensor) -> Tensor:
    """Axis-angle vectors (..., 3) (direction = axis, norm = angle in radians) -> (..., 4)."""
    _check_last(axis_angle, 3, "axis_angle_to_quat: axis_angle")
    angle = axis_angle.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(a/2)/a, with its Taylor expansion near 0 so that gradients stay finite.
    small = angle < 1e-6
    safe = torch.where(small, torch.ones_like(angle), angle)
    k = torch.where(small, 0.5 - angle**2 / 48.0, torch.sin(half) / safe)
    return torch.cat([torch.cos(half), axis_angle * k], dim=-1)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternions (..., 4) -> rotation matrices (..., 3, 3)."""
    _check_last(q, 4, "quat_to_matrix: q")
    w, x, y, z = q.unbind(-1)
    two = 2.0
    m = torch.stack(
        (
            1 - two * (y * y + z * z), two * (x * y - z * w), two * (x * z + y * w),
            two * (x * y + z * w), 1 - two * (x * x + z * z), two * (y * z - x * w),
            two * (x * z - y * w), two * (y * z + x * w), 1 - two * (x * x + y * y),
        ),
        dim=-1,
    )
    return m.reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(m: Tensor) -> Tensor:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) with w >= 0.

    Uses the largest of the four candidate denominators (Shepperd's method) for stability.
    """
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"matrix_to_quat: expected (..., 3, 3), got {tuple(m.shape)}")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4*w^2, 4*x^2, 4*y^2, 4*z^2
    sq = torch.stack(
        (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22),
        dim=-1,
    ).clamp_min(0.0)
    r = torch.sqrt(sq)  # 2|w|, 2|x|, 2|y|, 2|z|
    # Each row: the quaternion times 2*(its component of that row), i.e. 4 * q * q_k.
    cands = torch.stack(
        (
            torch.stack((sq[..., 0], m21 - m12, m02 - m20, m10 - m01), -1),
            torch.stack((m21 - m12, sq[..., 1], m10 + m01, m02 + m20), -1),
            torch.stack((m02 - m20, m10 + m01, sq[..., 2], m12 + m21), -1),
            torch.stack((m10 - m01, m20 + m02, m21 + m12, sq[..., 3]), -1),
        ),
        dim=-2,
    )
    cands = cands / (2.0 * r[..., None]).clamp_min(1e-12)
    best = r.argmax(dim=-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = qnormalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_to_cont6d(q: Tensor) -> Tensor:
    """(..., 4) -> (..., 6): first two columns of the rotation matrix (HumanML3D order)."""
    m = quat_to_matrix(q)
    return torch.cat([m[..., :, 0], m[..., :, 1]], dim=-1)


def cont6d_to_matrix(d6: Tensor) -> Tensor:
    """(..., 6) continuous 6-D rotations -> (..., 3, 3) by Gram-Schmidt (HumanML3D order)."""
    _check_last(d6, 6, "cont6d_to_matrix: d6")
    x = d6[..., 0:3]
    x = x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    z = torch.linalg.cross(x, d6[..., 3:6], dim=-1)
    z = z / z.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    y = torch.linalg.cross(z, x, dim=-1)
    return torch.stack([x, y, z], dim=-1)


def cont6d_to_quat(d6: Tensor) -> Tensor:
    """(..., 6) -> (..., 4)."""
    return matrix_to_quat(cont6d_to_matrix(d6))


def _axis_matrix(angle: Tensor, axis: str) -> Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    rows = {
        "X": (one, zero, zero, zero, c, -s, zero, s, c),
        "Y": (c, zero, s, zero, one, zero, -s, zero, c),
        "Z": (c, -s, zero, s, c, zero, zero, zero, one),
    }[axis]
    return torch.stack(rows, dim=-1).reshape(*angle.shape, 3, 3)


def euler_to_matrix(angles: Tensor, order: str = "ZYX") -> Tensor:
    """Euler angles (..., 3) in radians, listed in `order`, -> (..., 3, 3).

    The matrix is the product in the listed order, R = R_order[0] @ R_order[1] @ R_order[2],
    which is how BVH rotation channels compose.
    """
    _check_last(angles, 3, "euler_to_matrix: angles")
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"euler_to_matrix: order must be a permutation of 'XYZ', got {order!r}")
    m = _axis_matrix(angles[..., 0], order[0])
    m = m @ _axis_matrix(angles[..., 1], order[1])
    return m @ _axis_matrix(angles[..., 2], order[2])


def matrix_to_euler(m: Tensor, order: str = "ZYX") -> Tensor:
    """Rotation matrices (..., 3, 3) -> Euler angles (..., 3) in radians, inverse of
    `euler_to_matrix` for the same order (only "ZYX" and "XYZ" are supported).

    At gimbal lock (middle angle at +-90 degrees, within sqrt(eps) of the dtype) the first
    and last angles are not separable; the last is set to 0 and the first carries the turn.
    """
    locked_below = torch.finfo(m.dtype).eps ** 0.5 if m.is_floating_point() else 1e-6
    if order == "ZYX":  # R = Rz Ry Rx
        y = torch.asin((-m[..., 2, 0]).clamp(-1.0, 1.0))
        locked = torch.hypot(m[..., 0, 0], m[..., 1, 0]) < locked_below
        x = torch.where(locked, torch.zeros_like(y), torch.atan2(m[..., 2, 1], m[..., 2, 2]))
        z = torch.where(locked, torch.atan2(-m[..., 0, 1], m[..., 1, 1]),
                        torch.atan2(m[..., 1, 0], m[..., 0, 0]))
        return torch.stack((z, y, x), dim=-1)
    if order == "XYZ":  # R = Rx Ry Rz
        y = torch.asin(m[..., 0, 2].clamp(-1.0, 1.0))
        locked = torch.hypot(m[..., 0, 0], m[..., 0, 1]) < locked_below
        x = torch.where(locked, torch.atan2(m[..., 2, 1], m[..., 1, 1]),
                        torch.atan2(-m[..., 1, 2], m[..., 2, 2]))
        z = torch.where(locked, torch.zeros_like(y), torch.atan2(-m[..., 0, 1], m[..., 0, 0]))
        return torch.stack((x, y, z), dim=-1)
    raise ValueError(f"matrix_to_euler: unsupported order {order!r}; use 'ZYX' or 'XYZ'")

"""Poses of world-model items: a position and a unit quaternion, relative to the parent item."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Self

__all__ = ["Pose"]


@dataclass(frozen=True, slots=True)
class Pose:
    """A rigid transform: where a child frame is, seen from its parent frame.

    Positions are metres; the orientation is a unit quaternion (``qw`` the scalar part),
    normalised on construction. Build one from Euler angles with :meth:`from_euler`.

    Attributes:
        x: Position along the parent's x axis.
        y: Position along the parent's y axis.
        z: Position along the parent's z axis.
        qx: Quaternion, x part.
        qy: Quaternion, y part.
        qz: Quaternion, z part.
        qw: Quaternion, scalar part.

    Raises:
        ValueError: If a value is not a finite number or the quaternion is zero.
    """

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    qx: float = 0.0
    qy: float = 0.0
    qz: float = 0.0
    qw: float = 1.0

    def __post_init__(self) -> None:
        values = (self.x, self.y, self.z, self.qx, self.qy, self.qz, self.qw)
        for value in values:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"a pose holds numbers, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"a pose holds finite numbers, got {value!r}")
        norm = math.sqrt(self.qx**2 + self.qy**2 + self.qz**2 + self.qw**2)
        if norm < 1e-9:
            raise ValueError("the orientation quaternion is zero")
        if self.qw < 0:  # one canonical sign: q and -q are the same rotation
            norm = -norm
        if norm != 1.0 and abs(norm - 1.0) < 1e-12:
            norm = 1.0  # normalised already: keep the bits (a pose must survive the wire)
        for name in ("qx", "qy", "qz", "qw"):
            object.__setattr__(self, name, float(getattr(self, name)) / norm)
        for name in ("x", "y", "z"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @classmethod
    def from_euler(
        cls,
        x: float = 0.0,
        y: float = 0.0,
        z: float = 0.0,
        roll: float = 0.0,
        pitch: float = 0.0,
        yaw: float = 0.0,
    ) -> Self:
        """A pose from a position and roll, pitch, yaw.

        The angles are radians: rotations about the fixed x, y, z axes, applied in that order
        (as in ROS).

        Args:
            x: Metres.
            y: Metres.
            z: Metres.
            roll: About x.
            pitch: About y.
            yaw: About z.

        Returns:
            The pose.

        Raises:
            ValueError: If a value is not a finite number.
        """
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        return cls(
            x,
            y,
            z,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        )

    def euler(self) -> tuple[float, float, float]:
        """The orientation as roll, pitch, yaw (radians), the inverse of :meth:`from_euler`.

        Returns:
            ``(roll, pitch, yaw)``.
        """
        qx, qy, qz, qw = self.qx, self.qy, self.qz, self.qw
        roll = math.atan2(2 * (qw * qx + qy * qz), 1 - 2 * (qx * qx + qy * qy))
        pitch = math.asin(max(-1.0, min(1.0, 2 * (qw * qy - qz * qx))))
        yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
        return roll, pitch, yaw

    @property
    def yaw(self) -> float:
        """The heading about z, radians."""
        return self.euler()[2]

    def rotate(self, vx: float, vy: float, vz: float) -> tuple[float, float, float]:
        """Rotate a vector by this pose's orientation.

        Args:
            vx: x.
            vy: y.
            vz: z.

        Returns:
            The rotated vector.
        """
        qx, qy, qz, qw = self.qx, self.qy, self.qz, self.qw
        # v' = v + 2 q_v x (q_v x v + w v)
        tx = qy * vz - qz * vy + qw * vx
        ty = qz * vx - qx * vz + qw * vy
        tz = qx * vy - qy * vx + qw * vz
        return (
            vx + 2 * (qy * tz - qz * ty),
            vy + 2 * (qz * tx - qx * tz),
            vz + 2 * (qx * ty - qy * tx),
        )

    def compose(self, child: Pose) -> Pose:
        """This pose followed by ``child`` (a pose given in this pose's frame).

        Args:
            child: The pose relative to this one.

        Returns:
            The child's pose in this pose's parent frame.
        """
        dx, dy, dz = self.rotate(child.x, child.y, child.z)
        ax, ay, az, aw = self.qx, self.qy, self.qz, self.qw
        bx, by, bz, bw = child.qx, child.qy, child.qz, child.qw
        return Pose(
            self.x + dx,
            self.y + dy,
            self.z + dz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        )

    def inverse(self) -> Pose:
        """The pose of the parent frame seen from this one.

        Returns:
            The inverse transform.
        """
        conj = Pose(0.0, 0.0, 0.0, -self.qx, -self.qy, -self.qz, self.qw)
        px, py, pz = conj.rotate(-self.x, -self.y, -self.z)
        return Pose(px, py, pz, conj.qx, conj.qy, conj.qz, conj.qw)

    def as_tuple(self) -> tuple[float, float, float, float, float, float, float]:
        """``(x, y, z, qx, qy, qz, qw)``."""
        return (self.x, self.y, self.z, self.qx, self.qy, self.qz, self.qw)

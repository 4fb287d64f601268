"""Parametrised symmetric hexapods, for design studies and for reconstructing a table.

The layout is the usual 6-6 Gough-Stewart one, mirror-symmetric about the x-z plane:
base joints in three pairs centred at azimuths 0°, 120°, 240°, platform joints in three
pairs centred at 60°, 180°, 300°. Leg i joins base joint i to the neighbouring platform
joint, so legs (1, 6), (2, 5), (3, 4) are mirror images (y -> −y).

Each U-joint's fixed revolute axis lies in its mounting plane (horizontal: base plate,
platform plate), along the tangent of its joint circle turned about z by `base_axis_offset`
/ `platform_axis_offset` (rad; 0 = tangential, π/2 = radial). Legs 4-6 get the mirror image
of the axes of legs 3-1. Joint neutral directions are along the legs at home (see
`joint_bend`).
"""

import functools

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._errors import TableFileError
from .._table import Table

MIRROR = np.array([1.0, -1.0, 1.0])


def _ring(radius, azimuth_deg) -> Float[ArrayLike, "6 3"]:
    """Joint positions (6, 3) on a circle of `radius` at the given azimuths (deg), z = 0."""
    az = jnp.deg2rad(jnp.stack(azimuth_deg))
    return jnp.stack([radius * jnp.cos(az), radius * jnp.sin(az), jnp.zeros(6)], axis=-1)


def _axes(joints: Float[ArrayLike, "6 3"], offset) -> Float[ArrayLike, "6 3"]:
    """Horizontal unit axes (6, 3) at the joints' tangent direction turned by `offset` (rad)
    about z for legs 1-3, mirrored (y -> −y) for legs 6-4."""
    az = jnp.arctan2(joints[:3, 1], joints[:3, 0]) + jnp.pi / 2 + offset
    half = jnp.stack([jnp.cos(az), jnp.sin(az), jnp.zeros(3)], axis=-1)
    return jnp.concatenate([half, (half * MIRROR)[::-1]])


def symmetric_table(
    base_radius,
    platform_radius,
    base_half_angle,
    platform_half_angle,
    home_height,
    base_axis_offset=0.0,
    platform_axis_offset=0.0,
    *,
    platform_z=0.0,
    lead=0.0,
    hand=1.0,
    stroke=(0.0, jnp.inf),
    joint_angle_limit=jnp.inf,
    platform_mass=0.0,
    platform_cog=(0.0, 0.0, 0.0),
    name: str = "symmetric-hexapod",
) -> Table:
    """A mirror-symmetric 6-U(RP)U table. Lengths mm; half-angles in degrees; axis offsets in rad.

    `platform_z`: height of the platform joint plane in the platform frame (e.g. negative
    when the frame origin sits on the payload face above the joints). Differentiable in
    every numeric argument (all jnp), so a design can be fitted.
    """
    gb, gp = jnp.asarray(base_half_angle), jnp.asarray(platform_half_angle)
    b = _ring(base_radius, [gb, 120 - gb, 120 + gb, 240 - gb, 240 + gb, 360 - gb])
    a = _ring(platform_radius, [60 - gp, 60 + gp, 180 - gp, 180 + gp, 300 - gp, 300 + gp])
    a = a.at[:, 2].set(platform_z)
    nb = _axes(b, base_axis_offset)
    npf = _axes(a, platform_axis_offset)
    return Table(
        base_joints=b,
        platform_joints=a,
        base_axes=nb,
        platform_axes=npf,
        home_height=home_height,
        stroke=stroke,
        lead=lead,
        hand=hand,
        joint_angle_limit=joint_angle_limit,
        platform_mass=platform_mass,
        platform_cog=platform_cog,
        name=name,
    )


class SymmetricDesign(eqx.Module):
    """The parametrised symmetric hexapod as a pytree of design variables (float64 leaves).

    Geometry (`symmetric_table`'s arguments, angles in rad here): `base_radius`,
    `platform_radius` (mm), `base_half_angle`, `platform_half_angle` (rad: half the angle
    between the two joints of a pair), `home_height` (mm), `base_axis_offset`,
    `platform_axis_offset` (rad), `platform_z` (mm). Hardware leaves copied to the table:
    `lead` (6,) mm/rev, `hand` (6,) ±1, `stroke` (2,) mm, `joint_angle_limit` rad,
    `platform_mass` kg, `platform_cog` (3,) mm. `table()` builds the `Table`.
    """

    base_radius: Float[ArrayLike, ""]
    platform_radius: Float[ArrayLike, ""]
    base_half_angle: Float[ArrayLike, ""]
    platform_half_angle: Float[ArrayLike, ""]
    home_height: Float[ArrayLike, ""]
    base_axis_offset: Float[ArrayLike, ""]
    platform_axis_offset: Float[ArrayLike, ""]
    platform_z: Float[ArrayLike, ""]
    lead: Float[ArrayLike, "6"]
    hand: Float[ArrayLike, "6"]
    stroke: Float[ArrayLike, "2"]
    joint_angle_limit: Float[ArrayLike, ""]
    platform_mass: Float[ArrayLike, ""]
    platform_cog: Float[ArrayLike, "3"]
    name: str = eqx.field(static=True, default="symmetric-hexapod")

    def __init__(
        self,
        base_radius,
        platform_radius,
        base_half_angle,
        platform_half_angle,
        home_height,
        base_axis_offset=0.0,
        platform_axis_offset=0.0,
        platform_z=0.0,
        lead=0.0,
        hand=1.0,
        stroke=(0.0, jnp.inf),
        joint_angle_limit=jnp.inf,
        platform_mass=0.0,
        platform_cog=(0.0, 0.0, 0.0),
        name: str = "symmetric-hexapod",
    ):
        f = functools.partial(jnp.asarray, dtype=jnp.float64)
        self.base_radius = f(base_radius)
        self.platform_radius = f(platform_radius)
        self.base_half_angle = f(base_half_angle)
        self.platform_half_angle = f(platform_half_angle)
        self.home_height = f(home_height)
        self.base_axis_offset = f(base_axis_offset)
        self.platform_axis_offset = f(platform_axis_offset)
        self.platform_z = f(platform_z)
        self.lead = jnp.broadcast_to(f(lead), (6,))
        self.hand = jnp.broadcast_to(f(hand), (6,))
        self.stroke = f(stroke)
        self.joint_angle_limit = f(joint_angle_limit)
        self.platform_mass = f(platform_mass)
        self.platform_cog = f(platform_cog)
        self.name = name

    def table(self) -> Table:
        """The `Table` of this design (zero lengths = home leg lengths)."""
        return symmetric_table(
            self.base_radius,
            self.platform_radius,
            jnp.rad2deg(self.base_half_angle),
            jnp.rad2deg(self.platform_half_angle),
            self.home_height,
            self.base_axis_offset,
            self.platform_axis_offset,
            platform_z=self.platform_z,
            lead=self.lead,
            hand=self.hand,
            stroke=self.stroke,
            joint_angle_limit=self.joint_angle_limit,
            platform_mass=self.platform_mass,
            platform_cog=self.platform_cog,
            name=self.name,
        )

    @classmethod
    def from_table(cls, table: Table, tol_mm: float = 1e-6) -> "SymmetricDesign":
        """The symmetric parameters of a table built this way (radii and pair angles from
        joints 1, axis offsets from the first legs' axes), checked by rebuilding it: a table
        that differs by more than `tol_mm` (joints, mm) or 1e-9 (axes) is refused."""
        b, a = np.asarray(table.base_joints), np.asarray(table.platform_joints)
        nb, npf = np.asarray(table.base_axes), np.asarray(table.platform_axes)
        az_b = np.arctan2(b[0, 1], b[0, 0])
        az_a = np.arctan2(a[0, 1], a[0, 0])

        def offset(axis, az):
            d = np.arctan2(axis[1], axis[0]) - (az + np.pi / 2)
            return float(np.arctan2(np.sin(d), np.cos(d)))

        design = cls(
            base_radius=float(np.mean(np.linalg.norm(b[:, :2], axis=-1))),
            platform_radius=float(np.mean(np.linalg.norm(a[:, :2], axis=-1))),
            base_half_angle=float(az_b),
            platform_half_angle=float(np.deg2rad(60.0) - az_a),
            home_height=table.home_height,
            base_axis_offset=offset(nb[0], az_b),
            platform_axis_offset=offset(npf[0], az_a),
            platform_z=float(a[0, 2]),
            lead=table.lead,
            hand=table.hand,
            stroke=table.stroke,
            joint_angle_limit=table.joint_angle_limit,
            platform_mass=table.platform_mass,
            platform_cog=table.platform_cog,
            name=table.name,
        )
        t = design.table()
        joints = max(
            float(np.abs(np.asarray(t.base_joints) - b).max()),
            float(np.abs(np.asarray(t.platform_joints) - a).max()),
        )
        axes = max(
            float(np.abs(np.asarray(t.base_axes) - nb).max()),
            float(np.abs(np.asarray(t.platform_axes) - npf).max()),
        )
        if joints > tol_mm or axes > 1e-9:
            raise TableFileError(
                f"table '{table.name}' is not a symmetric hexapod (rebuilt from its radii and "
                f"pair angles, joints differ by {joints:.3g} mm, axes by {axes:.3g}): vary its "
                "table leaves (base_joints, platform_joints, home_height, ...) instead"
            )
        return design

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

import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from .._table import Table

MIRROR = jnp.array([1.0, -1.0, 1.0])


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
    platform_z: float = 0.0,
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

"""The table model: geometry and hardware of a 6-U(RP)U hexapod as an equinox pytree."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._errors import TableFileError, is_concrete
from ._jit import device_array


def _f64(x, shape=None) -> Array:
    """`x` as a float64 array (broadcast to `shape`, if given); in numpy where concrete
    (`_jit.device_array`: no eager programs)."""
    if is_concrete(x):
        a = np.asarray(x, dtype=np.float64)
        return device_array(a if shape is None or a.shape == shape else np.broadcast_to(a, shape))
    x = jnp.asarray(x, dtype=jnp.float64)
    return x if shape is None else jnp.broadcast_to(x, shape)


class Table(eqx.Module):
    """Geometry and hardware of one hexapod. All lengths in mm, angles in radians.

    Leaves (all float64 arrays, so any of them can be differentiated or fitted):

    - `base_joints` (6, 3): base U-joint centres b_i, base frame.
    - `platform_joints` (6, 3): platform U-joint centres a_i^p, platform frame.
    - `base_axes` (6, 3): unit axis n_i of each base U-joint's base-fixed revolute, base frame.
    - `platform_axes` (6, 3): unit axis j_i^p of each platform U-joint's platform-fixed
      revolute, platform frame.
    - `zero_lengths` (6,): L0_i, joint-to-joint length at actuator zero (homing reference).
      Defaults to the home-pose leg lengths.
    - `home_height` (): z of the platform origin at home, base frame.
    - `lead` (6,): screw lead, mm/rev (>= 0; 0 = no passive term on that leg).
    - `hand` (6,): +1 right-hand screw, -1 left-hand.
    - `stroke` (2,): allowed joint-to-joint length [lo, hi].
    - `joint_angle_limit` (): largest U-joint bend from its home direction (inf = none).
    - `platform_mass` (): kg; `platform_cog` (3,): mm, platform frame.

    `name` is static metadata. Shapes are checked on construction; values (unit axes, axes not
    parallel to legs) by `check_table`, which `load_table` calls.
    """

    base_joints: Float[ArrayLike, "6 3"]
    platform_joints: Float[ArrayLike, "6 3"]
    base_axes: Float[ArrayLike, "6 3"]
    platform_axes: Float[ArrayLike, "6 3"]
    zero_lengths: Float[ArrayLike, "6"]
    home_height: Float[ArrayLike, ""]
    lead: Float[ArrayLike, "6"]
    hand: Float[ArrayLike, "6"]
    stroke: Float[ArrayLike, "2"]
    joint_angle_limit: Float[ArrayLike, ""]
    platform_mass: Float[ArrayLike, ""]
    platform_cog: Float[ArrayLike, "3"]
    name: str = eqx.field(static=True)

    def __init__(
        self,
        base_joints,
        platform_joints,
        base_axes,
        platform_axes,
        home_height,
        stroke,
        lead=0.0,
        hand=1.0,
        zero_lengths=None,
        joint_angle_limit=jnp.inf,
        platform_mass=0.0,
        platform_cog=(0.0, 0.0, 0.0),
        name: str = "table",
    ):
        self.base_joints = _f64(base_joints)
        self.platform_joints = _f64(platform_joints)
        self.base_axes = _f64(base_axes)
        self.platform_axes = _f64(platform_axes)
        self.home_height = _f64(home_height)
        self.stroke = _f64(stroke)
        self.lead = _f64(lead, (6,))
        self.hand = _f64(hand, (6,))
        self.joint_angle_limit = _f64(joint_angle_limit)
        self.platform_mass = _f64(platform_mass)
        self.platform_cog = _f64(platform_cog)
        self.name = name
        if zero_lengths is None:
            zero_lengths = jnp.linalg.norm(home_leg_vectors(self), axis=-1)
        self.zero_lengths = _f64(zero_lengths)

    def __check_init__(self):
        shapes = {
            "base_joints": (6, 3),
            "platform_joints": (6, 3),
            "base_axes": (6, 3),
            "platform_axes": (6, 3),
            "zero_lengths": (6,),
            "home_height": (),
            "stroke": (2,),
            "joint_angle_limit": (),
            "platform_mass": (),
            "platform_cog": (3,),
        }
        for field, shape in shapes.items():
            got = getattr(self, field).shape
            if got != shape:
                raise TableFileError(f"table '{field}' must have shape {shape}; got {got}")

    @property
    def signed_lead(self) -> Float[ArrayLike, "6"]:
        """hand · lead, mm/rev: positive for a right-hand screw, negative for a left-hand one."""
        if is_concrete(self.hand, self.lead):  # numpy: no eager program
            return device_array(np.asarray(self.hand) * np.asarray(self.lead))
        return self.hand * self.lead


def home_leg_vectors(table: Table) -> Float[ArrayLike, "6 3"]:
    """l_i at the home pose, base frame, mm. Shape (6, 3)."""
    parts = (table.home_height, table.platform_joints, table.base_joints)
    if is_concrete(*parts):  # numpy: no eager programs (the same sums, exactly)
        h, a, b = (np.asarray(x) for x in parts)
        return device_array(np.array([0.0, 0.0, 1.0]) * h + a - b)
    t = jnp.array([0.0, 0.0, 1.0]) * table.home_height
    return t + table.platform_joints - table.base_joints


def check_table(table: Table, *, axis_tol: float = 1e-6, min_axis_angle_deg: float = 1.0):
    """Value checks a table must pass before kinematics makes sense. Raises TableFileError.

    - joint axes are unit vectors (|n| = 1 within `axis_tol`), never zero;
    - no joint axis is within `min_axis_angle_deg` of its leg at home (the rod rotation is
      undefined there);
    - the home height is positive, the home leg lengths are positive and inside the stroke,
      and the stroke is ordered;
    - lead >= 0, hand = ±1, joint_angle_limit > 0, platform_mass >= 0.
    """
    if not is_concrete(table):
        return table
    problems = []
    for field in ("base_axes", "platform_axes"):
        norms = np.linalg.norm(np.asarray(getattr(table, field)), axis=-1)
        for i, n in enumerate(norms):
            if not np.isfinite(n) or n < 1e-12:
                problems.append(f"{field} row {i + 1} (leg {i + 1}) is a zero vector")
            elif abs(n - 1.0) > axis_tol:
                problems.append(
                    f"{field} row {i + 1} (leg {i + 1}) has length {n:.6g}; axes must be unit "
                    f"vectors (normalise it)"
                )
    for field in ("base_joints", "platform_joints", "zero_lengths", "lead", "hand", "stroke"):
        if not np.all(np.isfinite(np.asarray(getattr(table, field)))):
            problems.append(f"{field} has non-finite values")
    if problems:
        raise TableFileError("malformed table:\n  " + "\n  ".join(problems))

    home = np.asarray(home_leg_vectors(table))
    lengths = np.linalg.norm(home, axis=-1)
    u = home / lengths[:, None]
    sin_min = np.sin(np.deg2rad(min_axis_angle_deg))
    for field, axes in (
        ("base_axes", np.asarray(table.base_axes)),
        ("platform_axes", np.asarray(table.platform_axes)),
    ):
        s = np.linalg.norm(np.cross(axes, u), axis=-1)
        for i in np.flatnonzero(s < sin_min):
            problems.append(
                f"{field} row {i + 1} (leg {i + 1}) is parallel to its leg at home "
                f"(angle {np.rad2deg(np.arcsin(min(s[i], 1.0))):.3g} deg); the rod rotation is "
                f"undefined"
            )
    lo, hi = (float(v) for v in np.asarray(table.stroke))
    if float(table.home_height) <= 0:
        problems.append(f"home_height must be positive; got {float(table.home_height)}")
    if not lo < hi:
        problems.append(f"stroke must be [lo, hi] with lo < hi; got [{lo}, {hi}]")
    for i, length in enumerate(lengths):
        if not lo <= length <= hi:
            problems.append(
                f"leg {i + 1}: home length {length:.3f} mm lies outside the stroke [{lo}, {hi}]"
            )
    if np.any(np.asarray(table.lead) < 0):
        problems.append("lead must be >= 0 (use hand = 'left' for a left-hand screw)")
    if not np.all(np.isin(np.asarray(table.hand), (-1.0, 1.0))):
        problems.append("hand must be +1 (right) or -1 (left) for every leg")
    if not float(table.joint_angle_limit) > 0:
        problems.append("joint_angle_limit must be positive")
    if float(table.platform_mass) < 0:
        problems.append("platform_mass must be >= 0")
    if problems:
        raise TableFileError("malformed table:\n  " + "\n  ".join(problems))
    return table


def replace(table: Table, **changes) -> Table:
    """A copy of `table` with some leaves replaced (values converted to float64)."""
    names = list(changes)
    return eqx.tree_at(
        lambda t: [getattr(t, n) for n in names],
        table,
        [_f64(changes[n]) for n in names],
    )

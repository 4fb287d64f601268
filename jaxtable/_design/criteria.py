"""Design criteria: what a table design is worth over a required workspace, each a
differentiable function of the design.

Per pose q (one-pose kernel `pose_criteria`, batched with vmap), with the legs as lines
(u_i unit direction, m_i = R a_i × u_i moment arm about the platform origin, base axes) and
J the 6×6 matrix of rows [u_i, m_i] (∂L/∂(translation, rotation vector)):

- `coverage` (–): fraction of the poses whose margin min(L_i − lo, hi − L_i,
  (bend limit − bend_i)·ℓ) is ≥ 0 (mm; stroke and U-joint bend limits).
- `gci`, `min_lci` (–): mean and worst of the local condition index LCI = 1/κ_F(J_h),
  J_h = J diag(1, 1, 1, 1/ℓ, 1/ℓ, 1/ℓ) (ℓ the characteristic length, mm), with Angeles'
  Frobenius-norm condition number κ_F = ‖J_h‖_F ‖J_h⁻¹‖_F / 6: 1 for an isotropic Jacobian,
  0 at a singularity, between κ₂/6 and κ₂ for the 2-norm κ₂, and, unlike κ₂ (a ratio of
  singular values that is not differentiable where they cross), smooth everywhere, which a
  gradient-based design needs.
- `max_position_sigma_mm`, `max_rotation_sigma_arcsec`: worst RMS translation / rotation σ of
  the tolerance budget (spiral compensated; `errormap.budget_one`).
- `max_spiral_error_mm`: worst ‖J⁻¹ Δl2‖ (translation): the uncompensated passive spiral.
- `min_stiffness_translation_N_per_mm`: worst 1/λ_max(C_tt), C = K⁻¹, K = Jᵀ diag(k) J: the
  stiffness against a force at the platform origin with the platform free to rotate;
  `min_stiffness_rotation_Nmm_per_rad`: worst 1/λ_max(C_rr), against a moment.
- `max_leg_force_N`: worst max_i |F_i|, F = J⁻ᵀ·wrench for the weight of platform + payload
  plus m·a in the worst translational direction: |F0_i| + m a ‖(J⁻ᵀ G)_i‖.
- `max_motor_torque_Nm`: worst F_i·lead_i / (2π η).
- `max_motor_rpm`: worst 60·l̇_i / lead_i with l̇_i = v + ω‖m_i‖ (speed v, angular speed ω,
  both in their worst directions).
- `tolerance_cost` (–): Σ_s t_s^paper / t_s over the budget's sources: the cost of the
  tolerances if each source costs 1 at the paper's tolerance and cost ∝ 1/tolerance (6 for
  the paper's budget).
- `first_frequency_Hz`: at home, √λ_min(K, M) / (2π), M the spatial inertia of platform +
  payload about the platform origin.

Worst cases are reported exactly (max, min); for gradients `smooth=p` replaces them by the
p-norm (Σ xᵖ)^(1/p) (min: p → −p), scaled by the exact extreme so it never overflows. It is
on the safe side (a worst case never looks better than it is, so a design that meets a
smoothed constraint meets the exact one) and within a factor n^(1/p) of the exact value over
n poses. Coverage becomes the mean of sigmoid(margin/τ), τ = `coverage_width` mm. Both
converge to the exact values as p → ∞, τ → 0. Worst cases run over every required pose,
reachable or not: a design must serve the whole required workspace, and `coverage` says how
much of it it reaches. Angular acceleration and the leg's own inertia are not in the force
duty; leg-leg clearance is not modelled.
"""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from .._analysis.errormap import budget_one
from .._analysis.tolerances import SOURCES, Tolerances
from .._effects import gravity_wrench
from .._kinematics import HOME, joint_bend, leg_lengths, leg_lines
from .._linalg import (
    inv_small,
    largest_eigval_small,
    matmul_small,
    smallest_generalized_eigval,
)
from .._rotation import ARCSEC_PER_RAD, rotation_matrix
from .._table import Table
from .hardware import Hardware


@dataclass(frozen=True)
class Criterion:
    sense: str  # "max" (more is better) or "min"
    unit: str
    meaning: str


CRITERIA = {
    "coverage": Criterion("max", "", "fraction of the required workspace within limits"),
    "gci": Criterion("max", "", "global condition index (workspace mean of the LCI)"),
    "min_lci": Criterion("max", "", "worst local condition index"),
    "max_position_sigma_mm": Criterion("min", "mm", "worst RMS position σ of the budget"),
    "max_rotation_sigma_arcsec": Criterion("min", "arcsec", "worst RMS rotation σ"),
    "max_spiral_error_mm": Criterion("min", "mm", "worst uncompensated spiral position error"),
    "min_stiffness_translation_N_per_mm": Criterion("max", "N/mm", "worst force stiffness"),
    "min_stiffness_rotation_Nmm_per_rad": Criterion("max", "N·mm/rad", "worst moment stiffness"),
    "max_leg_force_N": Criterion("min", "N", "worst axial leg force"),
    "max_motor_torque_Nm": Criterion("min", "N·m", "worst motor torque"),
    "max_motor_rpm": Criterion("min", "rpm", "worst motor speed"),
    "first_frequency_Hz": Criterion("max", "Hz", "first natural frequency at home"),
    "tolerance_cost": Criterion("min", "", "tolerance cost, 1 per source at the paper's budget"),
}
"""Every criterion by its JSON key: sense (`max` = larger is better), unit, meaning."""


def _skew(v):
    return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def leg_matrix(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "6 6"]:
    """J (6, 6): row i = [u_i, R a_i × u_i], the rigid map from a platform twist (translation
    of the platform origin mm, rotation vector rad, base axes) to leg length changes, and the
    transpose of the map from leg forces to the wrench on the platform."""
    u, m = leg_lines(table, pose)
    return jnp.concatenate([u, m], axis=1)


def stiffness_matrix(
    table: Table, pose: Float[ArrayLike, "6"], leg_stiffness: Float[ArrayLike, "#6"] | float
) -> Float[ArrayLike, "6 6"]:
    """K = Jᵀ diag(k) J (6, 6) at `pose`, about the platform origin, base axes; rows/columns
    x, y, z, rx, ry, rz; blocks N/mm, N (coupling), N·mm/rad. Legs are axial springs k_i N/mm
    between ideal joints."""
    J = leg_matrix(table, pose)
    return J.T @ (jnp.broadcast_to(leg_stiffness, (6,))[:, None] * J)


def spatial_inertia(table: Table, hw: Hardware) -> Float[ArrayLike, "6 6"]:
    """M (6, 6) of platform + payload about the platform origin at home (kg, kg·mm, kg·mm²),
    for twists ordered as `stiffness_matrix`: [[m I, −m [c]×], [m [c]×, I_c − m [c]×²]]."""
    m = hw.moving_mass(table)
    c = table.platform_cog
    C = _skew(c)
    top = jnp.concatenate([m * jnp.eye(3), -m * C], axis=1)
    bottom = jnp.concatenate([m * C, jnp.diag(hw.inertia) - m * C @ C], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


def first_frequency(table: Table, hw: Hardware) -> Float[ArrayLike, ""]:
    """Lowest natural frequency at home, Hz: det(K − ω² M) = 0. K in N/mm-based units and M
    in kg/mm units give ω² in 1/s² × 10⁻³, hence the factor 1000."""
    K = stiffness_matrix(table, HOME, hw.leg_stiffness)
    lam = smallest_generalized_eigval(K, spatial_inertia(table, hw))
    return jnp.sqrt(1e3 * lam) / (2 * jnp.pi)


def pose_criteria(table: Table, hw: Hardware, pose: Float[ArrayLike, "6"]) -> dict:
    """Every per-pose quantity at one commanded pose (scalars; see the module table):
    margin mm, lci, position_sigma mm, rotation_sigma rad, spiral_error mm, stiffness_t N/mm,
    stiffness_r N·mm/rad, leg_force N, motor_torque N·m, motor_rpm."""
    J = leg_matrix(table, pose)
    Jinv = inv_small(J)  # one factorisation serves dexterity, stiffness and statics
    ell = hw.characteristic_length
    scale = jnp.concatenate([jnp.ones(3), jnp.full(3, 1.0 / ell)])
    # J_h = J diag(scale): ‖J_h⁻¹‖_F = ‖diag(1/scale) J⁻¹‖_F
    lci = 6.0 / jnp.sqrt(jnp.sum((J * scale) ** 2) * jnp.sum((Jinv / scale[:, None]) ** 2))
    C = Jinv @ (Jinv.T / hw.leg_stiffness[:, None])  # K⁻¹ = J⁻¹ diag(1/k) J⁻ᵀ
    k_t = 1.0 / largest_eigval_small(C[:3, :3])
    k_r = 1.0 / largest_eigval_small(C[3:, 3:])

    mass = hw.moving_mass(table)
    # the leg forces F solve Jᵀ F = wrench (`leg_forces`), with J's factorisation above
    f0 = matmul_small(Jinv.T, gravity_wrench(table, pose, hw.payload))
    rc = rotation_matrix(pose[3:]) @ table.platform_cog
    G = -mass * hw.acceleration * jnp.concatenate([jnp.eye(3), _skew(rc)])  # wrench per unit a
    B = Jinv.T @ G  # leg forces per unit acceleration
    force = jnp.abs(f0) + jnp.linalg.norm(B, axis=1)
    lead = table.lead
    torque = force * lead / (2 * jnp.pi * hw.efficiency) / 1000.0
    speed = hw.velocity + hw.angular_velocity * jnp.linalg.norm(J[:, 3:], axis=1)
    rpm = jnp.where(lead > 0, 60.0 * speed / jnp.where(lead > 0, lead, 1.0), 0.0)

    std, bias, _, _ = budget_one(table, hw.tolerances.sigmas(), pose, with_cond=False)

    L = leg_lengths(table, pose)
    stroke = jnp.minimum(L - table.stroke[0], table.stroke[1] - L)
    bend = (table.joint_angle_limit - joint_bend(table, pose)) * ell
    margin = jnp.minimum(jnp.min(stroke), jnp.min(bend))
    return {
        "margin": margin,
        "lci": lci,
        "position_sigma": jnp.linalg.norm(std[-1, :3]),
        "rotation_sigma": jnp.linalg.norm(std[-1, 3:]),
        "spiral_error": jnp.linalg.norm(bias[:3]),
        "stiffness_t": k_t,
        "stiffness_r": k_r,
        "leg_force": jnp.max(force),
        "motor_torque": jnp.max(torque),
        "motor_rpm": jnp.max(rpm),
    }


def _soft_max(x, p):
    """(Σ (x/x_max)ᵖ)^(1/p) · x_max for x ≥ 0: an upper bound, max ≤ · ≤ max·n^(1/p)."""
    top = jax.lax.stop_gradient(jnp.max(x))
    safe = jnp.where(top > 0, top, 1.0)
    return jnp.where(top > 0, safe * jnp.sum((x / safe) ** p) ** (1.0 / p), 0.0)


def _soft_min(x, p):
    """(Σ (x/x_min)⁻ᵖ)^(−1/p) · x_min for x > 0: a lower bound, min·n^(−1/p) ≤ · ≤ min."""
    low = jax.lax.stop_gradient(jnp.min(x))
    return low * jnp.sum((x / low) ** (-p)) ** (-1.0 / p)


def aggregate(per_pose: dict, smooth=None, coverage_width: Float[ArrayLike, ""] = 1.0) -> dict:
    """Workspace criteria (scalars, CRITERIA keys except `first_frequency_Hz`) from the
    per-pose quantities of `pose_criteria` batched over poses ((N,) each). `smooth=None`:
    exact worst cases; `smooth=p`: power means (see the module docstring)."""
    if smooth is None:
        hi, lo = jnp.max, jnp.min
        coverage = jnp.mean(per_pose["margin"] >= 0)
    else:

        def hi(x):
            return _soft_max(x, smooth)

        def lo(x):
            return _soft_min(x, smooth)

        coverage = jnp.mean(jax.nn.sigmoid(per_pose["margin"] / coverage_width))
    return {
        "coverage": coverage,
        "gci": jnp.mean(per_pose["lci"]),
        "min_lci": lo(per_pose["lci"]),
        "max_position_sigma_mm": hi(per_pose["position_sigma"]),
        "max_rotation_sigma_arcsec": hi(per_pose["rotation_sigma"]) * ARCSEC_PER_RAD,
        "max_spiral_error_mm": hi(per_pose["spiral_error"]),
        "min_stiffness_translation_N_per_mm": lo(per_pose["stiffness_t"]),
        "min_stiffness_rotation_Nmm_per_rad": lo(per_pose["stiffness_r"]),
        "max_leg_force_N": hi(per_pose["leg_force"]),
        "max_motor_torque_Nm": hi(per_pose["motor_torque"]),
        "max_motor_rpm": hi(per_pose["motor_rpm"]),
    }


def criteria(
    table: Table,
    hw: Hardware,
    poses: Float[ArrayLike, "N 6"],
    smooth=None,
    coverage_width: Float[ArrayLike, ""] = 1.0,
) -> dict:
    """Every criterion of CRITERIA (scalars) of one design over the required poses (N, 6),
    mm / rad. Differentiable in every leaf of `table` and `hw`; `smooth=p` gives the
    smoothed worst cases an optimiser should follow (see the module docstring)."""
    per_pose = jax.vmap(lambda q: pose_criteria(table, hw, q))(poses)
    out = aggregate(per_pose, smooth, coverage_width)
    out["first_frequency_Hz"] = first_frequency(table, hw)
    out["tolerance_cost"] = tolerance_cost(hw.tolerances)
    return out


def tolerance_cost(tol: Tolerances) -> Float[ArrayLike, ""]:
    """Σ_s t_s^paper / t_s: each source costs 1 at the paper's tolerance, ∝ 1/tolerance."""
    paper = Tolerances()
    return sum(getattr(paper, s) / jnp.asarray(getattr(tol, s)) for s in SOURCES)

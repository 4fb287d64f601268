"""The free-parameter vocabulary: which leaves of a model (table, effects) a fit, a
sensitivity, a posterior or a tolerance budget may vary, how they are spelled, read and
replaced, and how their elements are named in reports.

A parameter name is either a table leaf (`"base_joints"`, `"zero_lengths"`, `"lead"`, ...) or
`"effect.field"` for a field of an effect in the model (`"spiral.lead"`,
`"lead_scale.eps"`). A per-leg field of an effect that identical cylinders share (the
effect's `shared_fields`: one expansion coefficient, one stiffness) may also be fitted as one
number for all six legs, `"effect.field[all]"` (`"thermal.alpha[all]"`): one scalar step
added to every leg's value (the model still holds six values, all moved together). Element
names are of two kinds:

- keys (stable, for code, JSON and lookups): `zero_lengths[3]`, `base_joints[2].y`,
  `spiral.lead[1]`, and for joint sets fitted modulo rigid motions (the gauge, see
  `jaxtable._calibration.fit`) `base_joints.g7`;
- labels (for people): `leg 3 zero length L0`, `base joint 2 y`, `spiral lead, leg 1`, and for
  a gauge coordinate the joint displacements it moves most (`base joints: non-rigid mode 7
  [+0.61 joint 3 x, -0.55 joint 4 y, ...]`; `short_label` drops the bracket).
"""

import equinox as eqx
import jax
import numpy as np

from ._effects import MODEL_EFFECTS

GEOMETRY = ("base_joints", "platform_joints", "zero_lengths")
"""The 42 geometric parameters (b_i, a_i^p, L0_i): the default free set of every fit."""

PAPER_42 = ("zero_lengths", "platform_joints", "base_joints")
"""The same 42 in the paper's e_p order [dl (6), da^p (18), db (18)]."""

JOINTS = ("base_joints", "platform_joints")
"""The joint sets (6, 3): fitted modulo rigid motions when an instrument frame is estimated."""

TABLE_LEAVES = (
    "base_joints",
    "platform_joints",
    "base_axes",
    "platform_axes",
    "zero_lengths",
    "home_height",
    "lead",
    "hand",
)
"""Table leaves a sensitivity or fit may vary."""

NUISANCE = ("frame", "target")
"""Instrument parameters estimated with every fit (not model parameters)."""

UNITS = {
    "lead": "mm/rev",
    "eps": "",
    "w": "mm",
    "a": "mm",
    "b": "mm",
    "alpha": "1/K",
    "flex": "mm/N",
    "offsets": "mm",
}
"""Units of the library effects' fields (field name -> unit)."""

XYZ = ("x", "y", "z")
POSE = ("x", "y", "z", "roll", "pitch", "yaw")

_LEAF_LABEL = {
    "base_joints": "base joint",
    "platform_joints": "platform joint",
    "base_axes": "base axis",
    "platform_axes": "platform axis",
    "zero_lengths": "zero length L0",
    "lead": "screw lead",
    "hand": "screw hand",
    "home_height": "home height",
}


SHARED = "[all]"
"""Suffix of a parameter fitted as one number for all legs (`thermal.alpha[all]`), and of an
effect's shared form (`thermal[all]`: the effect with its `shared_fields` tied)."""


def is_shared(name: str) -> bool:
    """Whether a parameter name (or an effect form) is the one-number-for-all-legs form."""
    return name.endswith(SHARED)


def leaf(name: str) -> str:
    """The model leaf a parameter name moves: `thermal.alpha[all]` -> `thermal.alpha`."""
    return name[: -len(SHARED)] if is_shared(name) else name


def split(name: str) -> tuple[str | None, str]:
    """`"effect.field"` -> (effect, field); a table leaf -> (None, leaf); a shared parameter
    `"effect.field[all]"` -> (effect, field)."""
    effect, dot, field = leaf(name).partition(".")
    return (effect, field) if dot else (None, leaf(name))


def form_effect(form: str) -> str:
    """The effect of a form: `thermal[all]` -> `thermal`, `lead_scale[3]` -> `lead_scale`,
    `thermal` -> `thermal`."""
    return form.partition("[")[0]


def leg_of(form: str) -> int | None:
    """The leg (1-based) of a one-leg form (`"lead_scale[3]"` -> 3); None for other forms."""
    index = form.partition("[")[2][:-1]
    return int(index) if index.isdigit() else None


def effect_forms(effect: str) -> tuple[str, ...]:
    """The forms an effect can be fitted in: its per-leg form (`"thermal"`) and, when it has
    `shared_fields`, its shared form (`"thermal[all]"`: those fields one number for all
    legs, its other fields per leg)."""
    shared = MODEL_EFFECTS[effect].shared_fields
    return (effect, effect + SHARED) if shared else (effect,)


def leg_forms(effect: str) -> tuple[str, ...]:
    """The one-leg forms of an effect one cylinder can have alone (`one_leg`: a defect of
    its own screw or nut): `("lead_scale[1]", ..., "lead_scale[6]")`, each the effect on that
    leg with the other legs' fields zero; () for the others."""
    return tuple(f"{effect}[{i}]" for i in range(1, 7)) if MODEL_EFFECTS[effect].one_leg else ()


def effect_parameters(form: str) -> tuple[str, ...]:
    """The parameter names of a library effect form: `("spiral.lead",)`, `("periodic_lead.a",
    "periodic_lead.b")`, ...; a shared form's shared fields with the suffix
    (`"thermal[all]"` -> `("thermal.alpha[all]",)`); a one-leg form's element keys
    (`"periodic_lead[2]"` -> `("periodic_lead.a[2]", "periodic_lead.b[2]")`)."""
    effect = form_effect(form)
    cls = MODEL_EFFECTS[effect]
    leg = leg_of(form)
    if leg is not None:
        return tuple(f"{effect}.{f}[{leg}]" for f in cls.fields)
    tied = cls.shared_fields if is_shared(form) else ()
    return tuple(f"{effect}.{f}" + (SHARED if f in tied else "") for f in cls.fields)


def form_keys(keys, form: str) -> list[str]:
    """The element keys, among `keys`, of an effect form's parameters: `thermal[all]` ->
    `["thermal.alpha[all]"]`, `thermal` -> `["thermal.alpha[1]", ..., "thermal.alpha[6]"]`."""
    names = effect_parameters(form)
    return [k for k in keys if k in names or (not is_shared(k) and k.partition("[")[0] in names)]


def with_form(model, form: str) -> list:
    """The model (a list of effect forms) with `form` in it, in place of another form of the
    same effect (a shared form upgraded to per leg, one-leg forms to per leg); a one-leg form
    joins the effect's other one-leg forms (`lead_scale[2]` beside `lead_scale[5]`)."""
    effect = form_effect(form)
    beside = leg_of(form) is not None
    return [m for m in model if form_effect(m) != effect or (beside and leg_of(m))] + [form]


def form_label(form: str) -> str:
    """A person's name for an effect form: `thermal[all]` -> `thermal (one alpha for all
    legs)`, `lead_scale[3]` -> `lead_scale (leg 3 alone)`; a per-leg form is its name."""
    leg = leg_of(form)
    if leg is not None:
        return f"{form_effect(form)} (leg {leg} alone)"
    if not is_shared(form):
        return form
    effect = form_effect(form)
    fields = ", ".join(MODEL_EFFECTS[effect].shared_fields)
    return f"{effect} (one {fields} for all legs)"


def check(table, effects, names, *, allow_shared: bool = False) -> None:
    """Raise ValueError naming any entry of `names` that is not a parameter of the model
    (`effects`: a mapping name -> effect Module). Shared parameters (`thermal.alpha[all]`)
    only where `allow_shared` (fits; a sensitivity is per element)."""
    for name in names:
        effect, field = split(name)
        if is_shared(name) and not allow_shared:
            raise ValueError(f"parameter '{name}': a shared parameter can only be fitted")
        if is_shared(name):
            cls = type(effects.get(effect)) if effect is not None else None
            if effect is None or field not in getattr(cls, "shared_fields", ()):
                raise ValueError(
                    f"parameter '{name}': only an effect's shared fields can be fitted as one "
                    f"number for all legs (e.g. thermal.alpha[all], compliance.flex[all])"
                )
        if effect is not None:
            if effect not in effects:
                raise ValueError(
                    f"parameter '{name}': no effect '{effect}' in the model (effects: "
                    f"{', '.join(sorted(effects)) or 'none'}); pass it in `effects=`"
                )
            if not isinstance(getattr(effects[effect], field, None), jax.Array):
                raise ValueError(
                    f"parameter '{name}': effect '{effect}' has no array field '{field}'"
                )
        elif name not in TABLE_LEAVES:
            raise ValueError(
                f"unknown parameter '{name}': use a table leaf ({', '.join(TABLE_LEAVES)}) or "
                f"'effect.field' (e.g. spiral.lead)"
            )


def as_names(names) -> tuple:
    """A list of names a person passed, as a tuple: one string is one name (`"zero_lengths"`,
    not its letters)."""
    return (names,) if isinstance(names, str) else tuple(names)


def check_distinct(names, what: str = "parameter") -> None:
    """Raise ValueError where a list a person wrote names one thing twice: a repeated entry,
    or a field in both its forms (`spiral.lead` and `spiral.lead[all]`: the shared column
    is the sum of the per-leg ones, so one direction of the pair is free)."""
    seen = set()
    for name in names:
        if name in seen:
            raise ValueError(f"{what} '{name}' is given twice")
        seen.add(name)
    for name in names:
        if is_shared(name) and leaf(name) in seen:
            raise ValueError(
                f"'{leaf(name)}' and '{name}' are two forms of one field: fit it per leg or "
                f"as one number for all legs, not both"
            )


def get(table, effects, name: str):
    """The array of parameter `name` in the model (table, effects); a shared parameter
    (`thermal.alpha[all]`) -> the per-leg leaf it moves."""
    effect, field = split(name)
    return getattr(table if effect is None else effects[effect], field)


def replace(table, effects, values: dict):
    """(table, effects) with the parameters named in `values` replaced (name -> array);
    `effects` is copied, never changed in place. Differentiable (eqx.tree_at)."""
    model = (table, dict(effects))
    names = list(values)
    if not names:
        return model
    return eqx.tree_at(
        lambda m: [get(m[0], m[1], n) for n in names], model, [values[n] for n in names]
    )


def element_keys(name: str, shape: tuple) -> list[str]:
    """Stable keys of the elements of a parameter of `shape`: legs 1-based,
    `zero_lengths[3]`, `base_joints[2].y`, `home_height`."""
    if shape == ():
        return [name]
    if len(shape) == 1:
        return [f"{name}[{i + 1}]" for i in range(shape[0])]
    cols = XYZ if shape[1] == 3 else tuple(str(j + 1) for j in range(shape[1]))
    return [f"{name}[{i + 1}].{cols[j]}" for i in range(shape[0]) for j in range(shape[1])]


def label(key: str) -> str:
    """A person's name for an element key: `base_joints[2].y` -> `base joint 2 y`,
    `zero_lengths[3]` -> `leg 3 zero length L0`, `spiral.lead[1]` -> `spiral lead, leg 1`,
    `frame[2].yaw` -> `instrument frame (session 2) yaw`, `target.z` -> `target offset z`,
    `thermal.alpha[all]` -> `thermal alpha, all legs`.
    Gauge coordinates (`base_joints.g7`) need their basis: see `gauge_label`."""
    head, bracket, rest = key.partition("[")
    index, _, comp = rest.partition("]")
    comp = comp.lstrip(".")
    if head == "frame":
        return f"instrument frame (session {index}) {comp}"
    if head == "frame_drift":
        return f"instrument frame drift (session {index}) {comp}"
    if key.startswith("target."):
        return f"target offset {key.partition('.')[2]}"
    effect, field = split(head)
    if effect is None:
        name = _LEAF_LABEL.get(field, field.replace("_", " "))
        if not bracket:
            return name
        if field in JOINTS or field.endswith("_axes"):
            return f"{name} {index} {comp}".rstrip()
        return f"leg {index} {name}"
    base = f"{effect.replace('_', ' ')} {field}"
    if not bracket:
        return base
    if index == "all":
        return f"{base}, all legs"
    if comp.isdigit():  # (rows, 6) fields: one row per later session (rehoming offsets)
        return f"{base}, session {int(index) + 1}, leg {comp}"
    return f"{base}, leg {index}" + (f" {comp}" if comp else "")


def gauge_label(joint_set: str, index: int, basis: np.ndarray, top: int = 3) -> str:
    """Label of generalised coordinate `index` (0-based) of a joint set fitted modulo rigid
    motions: which joint displacements the coordinate moves most. `basis` (18, k): the
    orthonormal non-rigid basis (column i = the displacement of all 18 coordinates per unit
    of coordinate i, mm/mm)."""
    v = np.asarray(basis)[:, index]
    order = np.argsort(-np.abs(v))[:top]
    joint = "joint" if joint_set in JOINTS else joint_set
    parts = [f"{v[k]:+.2f} {joint} {k // 3 + 1} {XYZ[k % 3]}" for k in order]
    what = _LEAF_LABEL.get(joint_set, joint_set) + "s"
    return f"{what}: non-rigid mode {index + 1} [{', '.join(parts)}, ...]"


def short_label(text: str) -> str:
    """A label without its bracketed detail (for plot axes and one-line lists)."""
    return text.split(" [")[0]


def pose_to_file(pose) -> np.ndarray:
    """Poses (..., 6) in mm / rad -> mm / deg (files, CLI, JSON and tables)."""
    out = np.array(pose, dtype=float)
    out[..., 3:] = np.rad2deg(out[..., 3:])
    return out


def change_words(dof: int, value: float, std: float = float("nan")) -> str:
    """A change of pose DOF `dof` (0-5) and its σ in words, `value` and `std` in mm / rad:
    "x +28 ± 4.8 µm", "yaw +5.98 ± 1.9″" (no ± where `std` is NaN)."""
    scale, unit = (1e3, " µm") if dof < 3 else (np.rad2deg(1.0) * 3600.0, "″")
    sd = f" ± {scale * std:.2g}" if np.isfinite(std) else ""
    return f"{POSE[dof]} {scale * value:+.3g}{sd}{unit}"


def pose_from_file(pose) -> np.ndarray:
    """Poses (..., 6) in mm / deg -> mm / rad."""
    out = np.array(pose, dtype=float)
    out[..., 3:] = np.deg2rad(out[..., 3:])
    return out

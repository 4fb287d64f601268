"""Detection power of `diagnose`: how large must an effect be for a measurement plan and an
instrument to name it, and how often does noise alone name something?

`detection_power` answers on the linearisation of `diagnose`'s first round at the nominal
table — the regime the question is about, effects of a few σ. For a plan (`data`: the rows,
columns, σ, temperatures and sessions of a run) the base fit (geometry and instrument
frames) gives the full Jacobian J and the base fit's column space U. A planted effect with
parameter step θ adds the signal x = J θ to the readings; its amplitude is the largest |x|
over the measured cells in units of that cell's stated σ (peak signal / σ; a file without σ
columns: the noise model's default σ per column, as `setup` assigns it). Each
Monte Carlo trial draws residuals r = (I − U Uᵀ)(a x̂ + z) (z the noise with the rows'
correlation, exactly as the structure test and the dictionary threshold draw it) and applies
the first round's rules to them:

- a library effect (its columns X) is a candidate with Δχ² = ‖Q_Xᵀ r‖² / s²
  (Q_X a basis of (I − U Uᵀ) X, s² = ‖r‖² / dof: σ estimated, as `diagnose` does by default);
  it is accepted when ΔBIC = −Δχ² + rank · ln n_obs < −`bic_threshold` and it explains at least
  `min_share` of the excess χ² (with σ estimated: 3 √(2 dof)) or leaves no structure the
  structure test sees (the test on the residuals (I − Q_X Q_Xᵀ) r, against the null law of
  the fit with X added, at false-alarm rate `alpha`);
- a dictionary term is accepted when its penalised score Δχ² − k ln n_obs beats the
  dictionary-wide threshold (the same Monte Carlo law as `dictionary.screen`), absorbed
  terms excluded;
- when both are accepted the library effect is named, unless the term still beats the
  threshold on top of it and the library effect adds nothing (ΔBIC) on top of the term
  (`diagnose`'s priority rule, evaluated on the pair's joint basis), against every library
  form accepted: the best form that keeps its priority is named; when neither adds to
  the other, the library effect is named and the pair reported ambiguous (`flagged`);
- a library effect with a shared form (`spiral`, `thermal`, `compliance`: one coefficient for
  all legs) competes in both forms, a cylinder's own defect (`lead_scale`, `backlash`,
  `periodic_lead`) also on each leg alone (`lead_scale[3]`); any form names the effect.

Not modelled here: the held-out gain checks (`min_gain`, the term's grouped-fold gain), which
on data of this size bind only at amplitudes where the Δχ² rules already fail, and later
rounds. `Power.check` compares with full `diagnose` runs where that matters.
"""

import math
from dataclasses import dataclass, field

import jax
import numpy as np
from jax.flatten_util import ravel_pytree

from .. import _params as params
from .._calibration.fit import fit
from .._calibration.measurements import Measurements
from .._calibration.noise import fit_basis
from .._effects import EFFECTS
from .._table import Table
from .._threads import one_blas_thread
from .diagnose import applicable, discovery_setup
from .dictionary import Bases, candidates, null_max_scores
from .structure import agreements, features, neighbours, null_law, whitened


@dataclass
class Power:
    """Outcome of `detection_power`.

    - `labels` (L,) the planted effects; `truth` (L,) what naming each correctly means
      (a library effect's name, or a dictionary candidate's label);
    - `amplitudes` (A,) peak signal / σ;
    - `correct`, `wrong` (L, A): fraction of trials naming the planted effect first /
      naming something else first (the rest name nothing);
    - `wrong_names` (L, A): the most frequent wrong name ("" if none);
    - `flagged` (L, A): fraction of trials naming a library effect wrongly but reporting the
      planted term as ambiguous with it (part of `wrong`: the report offers the truth and a
      plan to tell them apart);
    - `false_discovery`: fraction of noise-only trials naming anything;
      `false_library`, `false_term`: the same split by kind;
    - `visible` (L,): ‖(I − U Uᵀ) x̂‖ for the planted signal x̂ of unit peak: what the base
      model cannot absorb; a one-coefficient term's Δχ² is noncentral χ²₁ with
      noncentrality (amplitude · visible)²;
    - `threshold`: the dictionary threshold; `trials`; `n_obs`; `scale` (L,): the planted
      module's peak signal / σ, to convert amplitudes into coefficients (`coefficient_at`).
    """

    labels: list
    truth: list
    amplitudes: np.ndarray
    correct: np.ndarray
    wrong: np.ndarray
    wrong_names: list
    false_discovery: float
    false_library: float
    false_term: float
    threshold: float
    trials: int
    n_obs: int
    visible: np.ndarray
    scale: np.ndarray = field(repr=False)
    flagged: np.ndarray | None = None

    def amplitude_at(self, label: str, level: float = 0.9) -> float:
        """The smallest amplitude (peak signal / σ) at which `label` is named with probability
        `level` (linear interpolation between the amplitudes run; NaN if never reached)."""
        p = self.correct[self.labels.index(label)]
        a = self.amplitudes
        hit = np.flatnonzero(p >= level)
        if hit.size == 0:
            return float("nan")
        k = hit[0]
        if k == 0:
            return float(a[0])
        return float(a[k - 1] + (level - p[k - 1]) * (a[k] - a[k - 1]) / (p[k] - p[k - 1]))

    def coefficient_at(self, label: str, amplitude: float) -> float:
        """The multiple of the planted parameter step that gives `amplitude`."""
        return float(amplitude / self.scale[self.labels.index(label)])


def _planted_step(st, planted: dict) -> tuple[np.ndarray, list]:
    """The flat θ step (P,) that takes the set-up's null effects to `planted` ({effect name:
    module}) and the keys it moves."""
    effects = {**st.effects, **planted}
    steps = {}
    for name in st.layout.free:
        effect, _ = params.split(name)
        if effect is None or effect not in planted or params.is_shared(name):
            steps[name] = jax.numpy.zeros_like(st.theta0[name])
            continue
        new = np.asarray(params.get(st.problem.nominal, effects, name), float)
        old = np.asarray(params.get(st.problem.nominal, st.effects, name), float)
        if new.shape != old.shape:  # e.g. a per-session field sized for one session
            if np.any(new):
                raise ValueError(
                    f"planted {name} has shape {new.shape}; these data need {old.shape}"
                )
            new = old
        steps[name] = (new - old).reshape(np.shape(st.theta0[name]))
    theta = {**{k: jax.numpy.zeros_like(v) for k, v in st.theta0.items()}, **steps}
    flat = np.asarray(ravel_pytree(theta)[0])
    return flat, [st.names[i] for i in np.flatnonzero(flat != 0)]


@one_blas_thread
def detection_power(
    nominal: Table,
    data: Measurements,
    planted: dict,
    amplitudes=(0.5, 1.0, 2.0, 3.0, 4.0, 6.0),
    *,
    trials: int = 1000,
    seed: int = 0,
    compensated: bool | None = None,
    library=None,
    discovery_alpha: float = 0.05,
    bic_threshold: float = 10.0,
    min_share: float = 0.3,
    alpha: float = 0.01,
    draws: int = 2000,
    chunk: int = 500,
    noise: str = "auto",
) -> Power:
    """Probability that `diagnose`'s first round names each planted effect, against its
    amplitude, for the plan and instrument of `data` (module docstring).

    `nominal`: the table; `data`: a run on that plan whose readings the nominal geometry
    explains up to noise (e.g. `simulate(nominal, true, ..., effects={})`): only its design
    (rows, columns, σ, context) and its noise level matter; `planted`: {label: {effect name:
    module}} — a library effect (e.g. `{"backlash": Backlash(np.ones(6))}`) or a dictionary
    term (`{"discovered": Discovered(s2=[0, 0, 1, 0, 0, 0])}`: it must be exactly one
    dictionary candidate); the module sets the shape, `amplitudes` (peak signal / σ) the
    size; `trials` per amplitude (also the noise-only trials); `draws`: Monte Carlo draws of
    the dictionary threshold and of each library form's structure-test null law; `alpha`:
    the structure test's false-alarm rate; `noise`: the σ the trials' noise has — "stated"
    (the data's σ columns, or the default σ where a file has none), "estimate" (each
    group's σ as the plan run's residuals show it: for σ stated wrong; one run's estimate is
    itself uncertain, ±6 % at 500 degrees of freedom, and biases every probability with it)
    or "auto" (default: stated where the data state σ, else estimated); other arguments as
    in `diagnose`."""
    if noise not in ("auto", "stated", "estimate"):
        raise ValueError(f"noise must be 'auto', 'stated' or 'estimate'; got {noise!r}")
    if trials < 1:
        raise ValueError(f"trials must be >= 1; got {trials}")
    amplitudes = np.asarray(amplitudes, float)
    if amplitudes.ndim != 1 or np.any(amplitudes < 0):
        raise ValueError("amplitudes must be a 1-D list of values >= 0 (peak signal / σ)")
    library = list(EFFECTS) if library is None else list(library)
    st = discovery_setup(nominal, data, compensated=compensated)
    effects_ok = [n for n in library if applicable(n, nominal, data)[0]]
    # the forms compete: per leg, shared, and a cylinder's own defect on each leg alone
    libs = [form for n in effects_ok for form in params.effect_forms(n) + params.leg_forms(n)]
    dict_c = candidates(st, data)
    labels = list(planted)
    truth, steps = [], []
    for label in labels:
        mods = planted[label]
        unknown = [n for n in mods if n not in st.effects]
        if unknown:
            raise ValueError(f"planted '{label}': unknown effect {unknown}")
        flat, keys = _planted_step(st, mods)
        if not keys:
            raise ValueError(f"planted '{label}' does not change any parameter")
        if "discovered" in mods:
            match = [c.label for c in dict_c if set(c.keys) == set(keys)]
            if len(mods) > 1 or not match:
                raise ValueError(
                    f"planted '{label}' must be exactly one dictionary candidate (moves {keys})"
                )
            truth.append(match[0])
        else:
            name = next(iter(mods))
            if len(mods) > 1:
                raise ValueError(f"planted '{label}' must be one effect")
            if name not in effects_ok:
                why = applicable(name, nominal, data)[1] or "not in the library searched"
                raise ValueError(f"planted '{label}': these data cannot name {name} ({why})")
            truth.append(name)
        steps.append(flat)

    # weights 1/σ as stated (amplitudes are in these units); with `noise` "estimate" the
    # whitening rescales the noise groups to what the plan run's residuals show (VCE), as the
    # screening does on data
    base = fit(st, st.free_mask(params.GEOMETRY), noise="fixed")
    stated = data.sigma is not None and bool(np.isfinite(np.asarray(data.sigma)).any())
    w = whitened(base, st, vce=noise == "estimate" or (noise == "auto" and not stated))
    J_stated = np.asarray(base.jacobian_full)
    Jf = J_stated * w.factor.reshape(-1, 1)
    index = {k: i for i, k in enumerate(st.names)}
    n_obs = int(w.mask.sum())
    pen = math.log(max(n_obs, 2))

    lib_cols = [[index[k] for k in params.form_keys(st.names, form)] for form in libs]
    lib_b = Bases.of(Jf, w.U, lib_cols)
    dict_b = Bases.of(Jf, w.U, [[index[k] for k in c.keys] for c in dict_c])
    k_lib = lib_b.rank * pen
    k_dict = np.array([len(c.keys) for c in dict_c], float) * pen
    fixed = dict_b.kept < 1e-3  # reproduced by the model: never tested
    null = null_max_scores(w, dict_b, k_dict, ~fixed, draws, seed + 1)
    threshold = float(np.quantile(null, 1.0 - discovery_alpha))
    excess = 3.0 * math.sqrt(2.0 * max(w.dof, 1.0))
    names = libs + [c.label for c in dict_c]
    # the structure test on each library form's fit: its neighbours and its null law
    nns = {f: neighbours(x, 3, w.rows) for f, x in features(st).items()}
    lib_q = [lib_b.Q[:, lib_b.bounds[i] : lib_b.bounds[i + 1]] for i in range(len(libs))]
    laws = [null_law(w, nns, draws, seed + 7919 * (i + 1), Q=q) for i, q in enumerate(lib_q)]

    def explains(res: np.ndarray, dl: np.ndarray, strong: np.ndarray) -> np.ndarray:
        """(b, L): each strong form explains `min_share` of the excess or leaves no
        structure (`diagnose`'s rule) for residuals `res` (b, M)."""
        ok = dl >= min_share * excess
        for li, (q, law) in enumerate(zip(lib_q, laws)):
            ask = np.flatnonzero(strong[:, li] & ~ok[:, li])
            if len(ask):
                r = res[ask] - (res[ask] @ q) @ q.T
                p = law.p_value(law.z(agreements(w, nns, r.reshape(len(ask), -1, 6))))
                ok[ask, li] = p >= alpha
        return ok

    def decide(res: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(b,) index into `names` of the first name for residuals `res` (b, M), −1: none;
        and (b,) the dictionary candidate reported ambiguous with a named library effect
        (index into the dictionary, −1: none)."""
        dl = lib_b.delta_chi2(res, w.dof)
        pl = dl - k_lib
        strong = pl > bic_threshold
        ok_l = strong & explains(res, dl, strong)
        best_l = np.argmax(np.where(ok_l, pl, -np.inf), axis=1)
        any_l = ok_l.any(axis=1)
        sd = dict_b.delta_chi2(res, w.dof) - k_dict
        live = ~(fixed | ((dict_b.kept < 0.1) & (sd <= threshold)))
        best_d = np.argmax(np.where(live, sd, -np.inf), axis=1)
        any_d = np.take_along_axis(np.where(live, sd, -np.inf), best_d[:, None], 1)[:, 0]
        any_d = any_d > threshold
        out = np.where(any_l, best_l, np.where(any_d, len(libs) + best_d, -1))
        amb = np.full(len(out), -1)
        both = np.flatnonzero(any_l & any_d)
        # the priority rule against every library form that passes (as `diagnose`): the
        # term goes first only if it does against each; else the best form that keeps
        # its priority is named
        keep = np.zeros((len(both), len(libs)), bool)
        tie = np.zeros((len(both), len(libs)), bool)
        for li in np.flatnonzero(ok_l[both].any(axis=0)):
            QL = lib_b.Q[:, lib_b.bounds[li] : lib_b.bounds[li + 1]]
            on = np.flatnonzero(ok_l[both, li])
            for di in np.unique(best_d[both[on]]):  # few distinct pairs: their joint basis
                k = on[best_d[both[on]] == di]
                QD = dict_b.Q[:, dict_b.bounds[di] : dict_b.bounds[di + 1]]
                QLD = fit_basis(np.concatenate([QL, QD], axis=1), 1e-8)
                r = res[both[k]]
                rr = np.sum(r**2, axis=1)
                pL, pD, pLD = (np.sum((r @ Q) ** 2, axis=1) for Q in (QL, QD, QLD))
                sL = (rr - pL) / max(w.dof - QL.shape[1], 1.0)
                sD = (rr - pD) / max(w.dof - QD.shape[1], 1.0)
                t_left = (pLD - pL) / sL - k_dict[di] > threshold
                l_left = (pLD - pD) / sD - lib_b.rank[li] * pen > bic_threshold
                keep[k, li] = ~(t_left & ~l_left)
                tie[k, li] = ~t_left & ~l_left
        pick = np.argmax(np.where(keep, pl[both], -np.inf), axis=1)
        kept = keep.any(axis=1)
        out[both] = np.where(kept, pick, len(libs) + best_d[both])
        amb[both] = np.where(kept & tie[np.arange(len(both)), pick], best_d[both], -1)
        return out, amb

    shapes, scale = [], []
    for label, flat in zip(labels, steps):
        x = J_stated @ flat
        peak = float(np.max(np.abs(x)))
        if peak == 0:
            raise ValueError(f"planted '{label}' is not seen by these data (zero signal)")
        shapes.append(x * w.factor.reshape(-1) / peak)
        scale.append(peak)

    def correct_name(named: np.ndarray, t: str) -> np.ndarray:
        if t in effects_ok:  # either form names the effect
            forms = [i for i, f in enumerate(libs) if params.form_effect(f) == t]
            return np.isin(named, forms)
        want = dict_c[[c.label for c in dict_c].index(t)]
        ok = np.array(
            [c.family == want.family and set(want.legs) <= set(c.legs) for c in dict_c] + [False]
        )  # the last entry: named nothing
        return ok[np.where(named >= len(libs), named - len(libs), -1)] & (named >= len(libs))

    A = len(amplitudes)
    correct = np.zeros((len(labels), A))
    wrong = np.zeros((len(labels), A))
    flagged = np.zeros((len(labels), A))
    wrong_names = [["" for _ in range(A)] for _ in labels]
    null_named = []
    for zz in w.null_draws(trials, seed + 2, batch=chunk):
        null_named.append(decide(zz.reshape(len(zz), -1))[0])
    null_named = np.concatenate(null_named)
    for li, x in enumerate(shapes):
        xp = x - w.U @ (w.U.T @ x)
        for ai, a in enumerate(amplitudes):
            named, amb = (
                np.concatenate(parts)
                for parts in zip(
                    *(
                        decide(a * xp + zz.reshape(len(zz), -1))
                        for zz in w.null_draws(trials, seed + 3 + ai, batch=chunk)
                    )
                )
            )
            ok = correct_name(named, truth[li])
            bad = (named >= 0) & ~ok
            correct[li, ai] = ok.mean()
            wrong[li, ai] = bad.mean()
            if truth[li] not in effects_ok:  # a term: was it offered as the ambiguous rival?
                offered = correct_name(np.where(amb >= 0, len(libs) + amb, -1), truth[li])
                flagged[li, ai] = (bad & offered).mean()
            if bad.any():
                vals, counts = np.unique(named[bad], return_counts=True)
                wrong_names[li][ai] = names[int(vals[np.argmax(counts)])]
    return Power(
        labels,
        truth,
        amplitudes,
        correct,
        wrong,
        wrong_names,
        float(np.mean(null_named >= 0)),
        float(np.mean((null_named >= 0) & (null_named < len(libs)))),
        float(np.mean(null_named >= len(libs))),
        threshold,
        trials,
        n_obs,
        np.asarray([np.linalg.norm(x - w.U @ (w.U.T @ x)) for x in shapes]),
        np.asarray(scale),
        flagged,
    )

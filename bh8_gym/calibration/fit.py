"""Fitting the simulated hand to a calibration log (`bh8 calibrate fit`).

The fitted parameters (`FIT_PARAMETERS`) are PlantParameters fields that are our estimates
(docs/modelling.md) and that the excitation's log can tell; each needs its evidence in the log
(a finger lifted by a weak drive, the spread moving, a squeeze the gauges felt). Some of the
estimates no log of motions can tell apart (`TIED`): every force in the model scales with the
motor's peak torque times a drive's efficiency, so the peak torque stays at Table 7's value and the
efficiencies carry the product; a heavier hand with stronger drives and less sensitive gauges
moves and reads exactly as the nominal one, so the links' mass stays at the CAD's. Others the
excitation cannot move far enough to show (`CHECKED`: the worm's slack, 9 counts; the motors'
no-load speed, above the envelope's fastest LCV); the fit measures their effect and says so.

The optimiser is SciPy's trust-region least squares (`scipy.optimize.least_squares`, "trf", with
bounds) on the logarithms of the parameters relative to their defaults. Its Jacobian is a forward
difference of `STEP` (5 %) in each, the replays of one iteration run in parallel (rollouts.py),
speculatively with the step's own replay. Uncertainties come from that Jacobian at the optimum,
each signal's residual variance inflated for its correlation from block to block (one standard
deviation); a parameter whose uncertainty is over `IDENTIFIED_UNCERTAINTY` is reported and left at
its default. The gauges' offsets are read off the rest phases (residuals.py).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from bh8_gym.calibration.residuals import REPLAY_OFFSETS, ResidualModel
from bh8_gym.plant.parameters import PlantParameters

STEP = 0.05  # forward-difference step in log(parameter): 5 %
IDENTIFIED_UNCERTAINTY = 0.10  # relative: a parameter known worse than this is not identified
CORRELATED = 0.99  # |correlation| above this: the log cannot tell the two apart
SENSITIVITY = 0.05  # a 5 % change that moves the scaled residuals' RMS by less than this tells nothing
REPLAY_MISMATCH_PERCENT = 2.0  # after the fit, a position RMS above this: the replay does not match the log
NOISE_PROBE = 1e-9  # log-parameter change of the noise probe


@dataclass(frozen=True)
class FitParameter:
    name: str
    evidence: str  # which Evidence flag the log must have
    tells: str  # what in the log tells it (the report says it)
    bounds: tuple[float, float] = (0.25, 4.0)  # factors of the default
    # A 5 % change must move the replay of these signals (residuals.py) by this many times their own
    # scatter (the noise probe's) for the parameter to be fitted: 3 for those the excitation is built
    # to show, 10 for the rest.
    signals: tuple = ("finger positions", "spread positions", "timing")
    noise_multiple: float = 3.0


FIT_PARAMETERS = (
    FitParameter("finger_drive_efficiency", "lifts", "how fast a weak drive lifts each finger (sweeps)"),
    FitParameter("spread_drive_efficiency", "spread", "how fast the spread goes at low gains (sweeps)"),
    FitParameter("spread_friction_torque", "spread", "where the spread's drive overcomes its friction (sweeps)",
                 (0.1, 10.0)),
    FitParameter("strain_gain", "squeezes", "the gauges' readings squeezing the calibration object",
                 signals=("strains",)),
)
CHECKED = (
    FitParameter("worm_slack", "lifts", "a finger falling back by its worm's slack (9 counts)", noise_multiple=10.0),
    FitParameter("motor_no_load_speed", "lifts", "a motor told to turn faster than it can", noise_multiple=10.0),
)
TIED = {
    "motor_peak_torque": "every drive's force is its peak torque times its efficiency: kept at Table 7's 5 N·cm, "
                         "the efficiencies carry the product",
    "link_mass_scale": "a heavier hand with stronger drives and less sensitive gauges moves and reads the same: "
                       "kept at the CAD's masses",
}


class FitError(ValueError):
    """A log the fit cannot use, or a fit that does not replay its log (the message says which)."""


@dataclass
class ParameterResult:
    name: str
    default: float
    value: float
    uncertainty: float | None  # one standard deviation, the parameter's unit
    status: str  # "fitted", "not identified: ..."
    tells: str = ""

    @property
    def identified(self) -> bool:
        return self.status == "fitted"


@dataclass
class FitResult:
    parameters: list
    offsets: tuple
    offset_uncertainty: tuple
    before: dict  # residual RMS by signal at the defaults
    after: dict  # and at the fit
    position_rms_before: float
    position_rms_after: float
    correlated: list = field(default_factory=list)  # (name, name, correlation)
    notes: list = field(default_factory=list)  # what the log could not tell, and why
    iterations: int = 0
    rollouts: int = 0
    seconds: float = 0.0
    nominal_signals: object = None
    fitted_signals: object = None
    noise: float = 0.0  # RMS change of the scaled residuals under the noise probe
    effects: dict = field(default_factory=dict)  # a 5 % change's effect over the replay's scatter, per parameter

    def hand_values(self) -> dict:
        """PlantParameters fields of the fitted hand (identified parameters and the offsets)."""
        values = {p.name: p.value for p in self.parameters if p.identified}
        values["strain_offsets"] = tuple(int(v) for v in self.offsets)
        return values

    def uncertainties(self) -> dict:
        values = {p.name: p.uncertainty for p in self.parameters if p.identified and p.uncertainty is not None}
        values["strain_offsets"] = tuple(float(v) for v in self.offset_uncertainty)
        return values


class _Evaluator:
    """Replays (through `rollouts`) at points of log-parameter space, cached, counted, with a progress bar."""

    def __init__(self, model: ResidualModel, rollouts, names: list[str], progress):
        self.model, self.rollouts, self.names, self.progress = model, rollouts, names, progress
        self.defaults = {name: float(getattr(PlantParameters(), name)) for name in names}
        self.cache: dict[bytes, object] = {}
        self.count = 0
        self.groups = None  # the residual groups compared (None: all)

    def hand(self, x: np.ndarray) -> dict:
        values = {name: self.defaults[name] * math.exp(float(v)) for name, v in zip(self.names, x)}
        values["strain_offsets"] = REPLAY_OFFSETS
        return values

    def signals(self, points: list[np.ndarray]) -> list:
        missing = [x for x in points if x.tobytes() not in self.cache]
        if missing:
            results = self.rollouts.map([self.hand(x) for x in missing])
            for x, result in zip(missing, results):
                self.cache[x.tobytes()] = result
            self.count += len(missing)
            if self.progress is not None:
                self.progress(len(missing))
        return [self.cache[x.tobytes()] for x in points]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self.model.vector(self.signals([x])[0], self.groups)

    def jacobian(self, x: np.ndarray, columns: list[int] | None = None) -> np.ndarray:
        columns = list(range(len(x))) if columns is None else columns
        points = [x.copy()]
        for j in columns:
            shifted = x.copy()
            shifted[j] += STEP
            points.append(shifted)
        results = [self.model.vector(s, self.groups) for s in self.signals(points)]
        base = results[0]
        jac = np.zeros((base.size, len(x)))
        for j, result in zip(columns, results[1:]):
            jac[:, j] = (result - base) / STEP
        return jac


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values ** 2))) if values.size else 0.0


def _covariance(model: ResidualModel, signals, jac: np.ndarray, groups) -> np.ndarray:
    """Sandwich covariance of log-parameters: each signal's residual variance, inflated by
    (1 + rho) / (1 - rho) for its lag-1 correlation rho (residuals of neighbouring blocks are not
    independent)."""
    found = model.groups(signals)
    weights = []
    for values in (found[name] for name in groups if name in found):
        variance = float(np.mean(values ** 2)) if values.size else 0.0
        rho = 0.0
        if values.size > 2 and np.std(values) > 0:
            rho = float(np.clip(np.corrcoef(values[:-1], values[1:])[0, 1], 0.0, 0.98))
        weights.append(np.full(values.size, variance * (1 + rho) / (1 - rho)))
    weights = np.concatenate(weights) if weights else np.zeros(0)
    bread = np.linalg.pinv(jac.T @ jac)
    meat = jac.T @ (jac * weights[:, None])
    return bread @ meat @ bread


def fit(log, rollouts, iterations: int = 12, progress=None, clock=time.monotonic) -> FitResult:
    """Fit FIT_PARAMETERS to `log` (a CalibrationLog) with `rollouts` (LocalRollouts/RayRollouts)."""
    from scipy.optimize import least_squares

    from bh8_gym.calibration.replay import observed

    started = clock()
    model = ResidualModel(observed(log), log.hand_clock)
    evidence = model.evidence
    notes = []
    if evidence.still_motors:
        notes.append("motor(s) " + ", ".join(map(str, evidence.still_motors)) + " did not move where the "
                     "excitation moves them")
    candidates, results = [], {}
    for parameter in FIT_PARAMETERS + CHECKED:
        default = float(getattr(PlantParameters(), parameter.name))
        if getattr(evidence, parameter.evidence):
            candidates.append(parameter)
        else:
            why = {"lifts": "no finger lifted in the log", "spread": "the spread did not move in the log",
                   "squeezes": "no squeeze of a calibration object the gauges felt (record with --object)",
                   }[parameter.evidence]
            results[parameter.name] = ParameterResult(parameter.name, default, default, None,
                                                      f"not identified: {why}", parameter.tells)
    if not candidates:
        raise FitError("the log holds nothing the fit can use: no finger lifted, the spread never moved and no "
                       "squeeze (was the excitation cut short?)")
    names = [p.name for p in candidates]
    evaluator = _Evaluator(model, rollouts, names, progress)
    x0 = np.zeros(len(names))
    # The noise probe: a change of a billionth moves the replay by what the simulation's own
    # sensitivity makes of it (contacts, stalls, a finger its weight helps along). A parameter whose
    # 5 % change does not stand its `noise_multiple` times above that tells nothing.
    probe = x0.copy()
    probe[0] = NOISE_PROBE
    shifted = [x0 + STEP * np.eye(len(names))[j] for j in range(len(names))]
    nominal, probed, *steps = evaluator.signals([x0, probe, *shifted])
    base = model.groups(nominal)
    scatter = {name: _rms(model.groups(probed)[name] - values) for name, values in base.items()}
    effects = [{name: _rms(model.groups(step)[name] - values) for name, values in base.items()} for step in steps]
    # Each parameter against the scatter of the signal (of those that can tell it) it moves most.
    def told_by(j):
        names = [name for name in candidates[j].signals if name in base] or list(base)
        return max(names, key=lambda name: effects[j][name] / max(scatter[name], SENSITIVITY))

    ratio = [effects[j][told_by(j)] / max(scatter[told_by(j)], SENSITIVITY) for j in range(len(candidates))]
    active = [j for j, parameter in enumerate(candidates) if ratio[j] >= parameter.noise_multiple]
    for j, parameter in enumerate(candidates):
        if j not in active:
            told = told_by(j)
            results[parameter.name] = ParameterResult(
                parameter.name, evaluator.defaults[parameter.name], evaluator.defaults[parameter.name], None,
                f"not identified: a 5 % change moves the {told} by {effects[j][told]:.2f}, "
                f"{ratio[j]:.1f} times the replay's own scatter there (needs {parameter.noise_multiple:g})",
                parameter.tells)
    # The squeezes' readings are compared only when the gauges' gain is fitted from them: otherwise
    # their scatter would only blur the rest.
    evaluator.groups = [name for name in base if name != "strains"
                        or any(candidates[j].name == "strain_gain" for j in active)]
    noise = _rms(model.vector(probed, evaluator.groups) - model.vector(nominal, evaluator.groups))
    jac0 = evaluator.jacobian(x0)
    if not active:
        raise FitError("no parameter changes the replay of this log measurably; nothing to fit")
    fitted = [candidates[j] for j in active]
    names = [p.name for p in fitted]
    evaluator.names = names
    lows = np.log([p.bounds[0] for p in fitted])
    highs = np.log([p.bounds[1] for p in fitted])
    evaluator.cache.clear()  # points are keyed by position in the (now shorter) parameter vector
    cached_jac = {np.zeros(len(names)).tobytes(): jac0[:, active]}
    evaluator.cache[np.zeros(len(names)).tobytes()] = nominal

    def residuals(x):
        jac = evaluator.jacobian(np.asarray(x, dtype=float))  # the step's own replay and its Jacobian at once
        cached_jac[np.asarray(x, dtype=float).tobytes()] = jac
        return evaluator.residuals(np.asarray(x, dtype=float))

    def jacobian(x):
        key = np.asarray(x, dtype=float).tobytes()
        if key not in cached_jac:
            cached_jac[key] = evaluator.jacobian(np.asarray(x, dtype=float))
        return cached_jac[key]

    solution = least_squares(residuals, np.zeros(len(names)), jac=jacobian, bounds=(lows, highs), method="trf",
                             x_scale=1.0, diff_step=None, max_nfev=iterations, xtol=2e-3, ftol=1e-4, gtol=1e-6)
    x = np.asarray(solution.x, dtype=float)
    best = evaluator.signals([x])[0]
    jac = jacobian(x)
    covariance = _covariance(model, best, jac, evaluator.groups)
    # One standard deviation: the residuals' own (statistical), and the resolution: the change whose
    # effect on the replay is its scatter (the noise probe's), whichever is larger in quadrature.
    effect_now = np.sqrt(np.mean((jac * STEP) ** 2, axis=0))
    resolution = STEP * noise / np.maximum(effect_now, 1e-12)
    sigma = np.sqrt(np.clip(np.diag(covariance), 0.0, None) + resolution ** 2)
    spread = np.sqrt(np.clip(np.diag(covariance), 1e-24, None))
    correlation = covariance / np.outer(spread, spread)
    correlated = []
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            if abs(correlation[a, b]) > CORRELATED:
                correlated.append((names[a], names[b], float(correlation[a, b])))
    tied = {name for pair in correlated for name in pair[:2]}
    for j, parameter in enumerate(fitted):
        default = evaluator.defaults[parameter.name]
        value = default * math.exp(x[j])
        uncertainty = value * float(sigma[j])
        at_bound = x[j] <= lows[j] + 1e-6 or x[j] >= highs[j] - 1e-6
        if parameter.name in tied:
            others = sorted({n for a, b, _ in correlated if parameter.name in (a, b) for n in (a, b)} - {parameter.name})
            status = f"not identified: the log cannot tell it apart from {', '.join(others)}"
        elif at_bound:
            status = f"not identified: the fit ran to its bound ({value:.4g}, {parameter.bounds[0]:g}-{parameter.bounds[1]:g} x default)"
        elif not sigma[j] <= IDENTIFIED_UNCERTAINTY:
            status = f"not identified: uncertain by {100 * sigma[j]:.0f} % (more than {100 * IDENTIFIED_UNCERTAINTY:.0f} %)"
        else:
            status = "fitted"
        results[parameter.name] = ParameterResult(parameter.name, default, value if status == "fitted" else default,
                                                  uncertainty, status, parameter.tells)
    for name, why in TIED.items():
        notes.append(f"{name}: {why}")
    order = [p.name for p in FIT_PARAMETERS + CHECKED]
    return FitResult(
        parameters=[results[name] for name in order], offsets=model.offsets(best),
        offset_uncertainty=model.offset_uncertainty(best), before=model.summary(nominal), after=model.summary(best),
        position_rms_before=model.position_rms(nominal), position_rms_after=model.position_rms(best),
        correlated=correlated, notes=notes, iterations=int(solution.nfev), rollouts=evaluator.count,
        seconds=clock() - started, nominal_signals=nominal, fitted_signals=best, noise=noise,
        effects={p.name: float(r) for p, r in zip(candidates, ratio)})

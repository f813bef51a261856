"""What `bh8 calibrate fit` tells its user: the text report and the plot of logged against simulated
traces, and the hand file's provenance."""
from __future__ import annotations

import numpy as np

from bh8_gym.calibration.excitation import EXCITATION_NAME
from bh8_gym.calibration.fit import FitResult
from bh8_gym.calibration.log_format import CalibrationLog
from bh8_gym.calibration.residuals import REPLAY_OFFSETS
from bh8_gym.protocol import FINGER_MOTORS

MOTOR_NAMES = {1: "F1", 2: "F2", 3: "F3", 4: "spread"}


def _number(value: float) -> str:
    return f"{value:.4g}"


def text_report(log: CalibrationLog, result: FitResult, where: str) -> str:
    """The fit's report (parameters, residuals per signal, what the log could not tell)."""
    header = log.header
    lines = [
        f"log: {log.path} (firmware {header.version_text}, {header.mounting}, "
        f"{header.calibration_object or 'no calibration object'}; {log.blocks:,} RealTime blocks; the hand's clock: "
        f"{log.hand_clock or 'not probed'})",
        f"fit: {result.rollouts} replays on {where} in {result.seconds:.0f} s, {result.iterations} least-squares "
        f"evaluations; the replays' own scatter {result.noise:.3f}",
        "",
        f"{'parameter':26s} {'default':>10s} {'fitted':>10s} {'± 1 sd':>9s}  status",
    ]
    for parameter in result.parameters:
        sd = "" if parameter.uncertainty is None or not parameter.identified else _number(parameter.uncertainty)
        shown = _number(parameter.value) if parameter.identified else "-"
        lines.append(f"{parameter.name:26s} {_number(parameter.default):>10s} {shown:>10s} {sd:>9s}  {parameter.status}")
        if parameter.identified:
            lines.append(f"{'':26s} {'':>10s} {'':>10s} {'':>9s}  (from {parameter.tells})")
    offsets = " ".join(str(v) for v in result.offsets)
    spread = " ".join(f"{v:.1f}" for v in result.offset_uncertainty)
    lines.append(f"{'strain_offsets':26s} {'100-140':>10s} {offsets:>10s} {spread:>9s}  fitted (the gauges at rest)")
    lines += ["", f"{'residual (RMS)':40s} {'defaults':>9s} {'fitted':>9s}"]
    for name, before in result.before.items():
        lines.append(f"{name:40s} {before:9.3f} {result.after.get(name, float('nan')):9.3f}")
    lines.append(f"{'position, all motors, % of range':40s} {result.position_rms_before:9.3f} "
                 f"{result.position_rms_after:9.3f}")
    if result.correlated:
        lines += ["", "told apart only together (|correlation| above 0.99):"]
        lines += [f"  {a} and {b}: {c:+.3f}" for a, b, c in result.correlated]
    lines += ["", "what this log cannot tell:"]
    lines += [f"  {p.name}: {p.status.removeprefix('not identified: ')}" for p in result.parameters if not p.identified]
    lines += [f"  {note}" for note in result.notes]
    return "\n".join(lines)


def fit_provenance(log: CalibrationLog, result: FitResult) -> dict:
    """The hand file's [fit] table."""
    timing = result.after.get("motion times, s")
    provenance = {
        "log": log.path[-400:], "log_sha256": log.digest,
        "excitation": f"{EXCITATION_NAME}/{log.header.excitation_version}", "hand_clock": log.hand_clock or "line",
        "fitted": [p.name for p in result.parameters if p.identified] + ["strain_offsets"],
        "not_identified": [p.name for p in result.parameters if not p.identified],
        "position_rms_percent": round(result.position_rms_after, 4),
        "position_rms_percent_before": round(result.position_rms_before, 4),
        "iterations": result.iterations, "rollouts": result.rollouts, "seconds": round(result.seconds, 1),
    }
    if "strain in the squeezes, counts" in result.after:
        provenance["strain_rms_counts"] = round(result.after["strain in the squeezes, counts"], 3)
    if timing is not None:
        provenance["timing_rms_s"] = round(timing, 4)
    return provenance


def plot_traces(path, log: CalibrationLog, observed, result: FitResult) -> None:
    """A PNG: each motor's logged position against the replays at the defaults and at the fit (the
    time axis is the simulated hand's), and each finger's gauge."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nominal, fitted = result.nominal_signals, result.fitted_signals
    times = fitted.times if fitted.times is not None and len(fitted.times) else np.arange(len(observed.positions))
    rows = len(observed.motors) + 1
    figure, axes = plt.subplots(rows, 1, figsize=(11, 2.0 * rows), sharex=True)
    for row, motor in enumerate(observed.motors):
        axis = axes[row]
        axis.plot(times, observed.positions[:, row], color="black", lw=1.0, label="logged")
        axis.plot(times, nominal.positions[:, row], color="tab:gray", lw=0.8, ls="--", label="simulated, defaults")
        axis.plot(times, fitted.positions[:, row], color="tab:red", lw=0.8, label="simulated, fitted")
        axis.set_ylabel(f"{MOTOR_NAMES.get(motor, motor)}\ncounts")
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)
    shift = np.array(result.offsets) - np.array(REPLAY_OFFSETS)
    axis = axes[-1]
    for index, motor in enumerate(FINGER_MOTORS):
        color = f"C{index}"
        axis.plot(times, observed.strains[:, index], color=color, lw=1.0, label=f"{MOTOR_NAMES[motor]} logged")
        axis.plot(times, fitted.strains[:, index] + shift[index], color=color, lw=0.8, ls=":",
                  label=f"{MOTOR_NAMES[motor]} fitted")
    axis.set_ylabel("gauge\ncounts")
    axis.set_xlabel("simulated hand's time, s")
    axis.legend(loc="upper right", fontsize=7, ncol=6)
    figure.suptitle(f"{log.path}: logged and replayed (position RMS {result.position_rms_before:.2f} % of range at "
                    f"the defaults, {result.position_rms_after:.2f} % fitted)", fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)

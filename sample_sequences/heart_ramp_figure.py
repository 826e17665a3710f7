"""The figure of README "A heart that speeds up" (``make heart-ramp``): the GE's sampled heart rate against the
true rate of the simulated pressure (the model file's beat lengths) and the KF's held rate, and the one-step
prediction errors of the GE, the KF and ``hold`` (1-s running means).

Usage: python heart_ramp_figure.py WORKDIR MODEL OUT.png  (WORKDIR holds meas.npz, fit.json, est_{ge,kf,hold}.npz)
"""

from __future__ import annotations

import json
from pathlib import Path
import sys

import numpy as np
import yaml


def main(work, model, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from heartcv.tracker.inputs import cardiac_phase
    from heartcv.tracker.io import read_estimates, read_measurements

    work = Path(work)
    meas = read_measurements(work / "meas.npz")
    t = meas.times
    pressure = yaml.safe_load(Path(model).read_text())["inputs"]["pressure"]
    _, _, period = cardiac_phase(t, pressure["heart_rate_bpm"], pressure.get("rr_intervals"))
    fit_bpm = 60 * json.loads((work / "fit.json").read_text())["heart_rate_hz"]
    ge = read_estimates(work / "est_ge.npz")
    hr, sd = 60 * ge.heart_rate[:, 0], 60 * ge.heart_rate[:, 1]
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 5.6), sharex=True, gridspec_kw={"height_ratios": [3, 2]})
    a.plot(t, 60 / period, "k-", lw=1.5, label="true rate (the simulated pressure's beats)")
    a.fill_between(t, hr - 2 * sd, hr + 2 * sd, color="C0", alpha=0.25, lw=0)
    a.plot(t, hr, "C0-", lw=1.2, label="GE: sampled rate (±2σ)")
    a.axhline(fit_bpm, color="C1", ls="--", lw=1.2, label=f"KF: the fitted rate, held ({fit_bpm:.1f} bpm)")
    a.axvspan(0, 4, color="0.85", lw=0, label="fitted frames (4 s)")
    a.set_ylabel("heart rate (bpm)")
    a.legend(loc="upper left", fontsize=8)
    a.grid(alpha=0.3)
    a.set_title("A heart that speeds up (paper patch, 72 → 96 bpm, pressure ignored)", fontsize=10)
    w = max(1, int(round(1.0 / np.median(np.diff(t)))))           # 1 s of frames
    for name, colour in (("hold", "0.5"), ("kf", "C1"), ("ge", "C0")):
        e = read_estimates(work / f"est_{name}.npz")
        err = 1e3 * np.nanmean(np.linalg.norm(e.predictions[1:] - meas.positions[1:], axis=-1), axis=1)
        run = np.convolve(err, np.ones(w) / w, mode="valid")
        b.plot(t[1 + w // 2: 1 + w // 2 + len(run)], run, color=colour, lw=1.2,
               label=name if name == "hold" else name.upper())
    b.set_xlabel("time (s)")
    b.set_ylabel("one-step error (mm, 1-s mean)")
    b.legend(fontsize=8, ncol=3)
    b.grid(alpha=0.3)
    b.set_xlim(0, t[-1])
    fig.tight_layout()
    fig.savefig(out, dpi=100)


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])

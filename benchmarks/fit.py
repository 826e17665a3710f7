"""Fit and tracking benchmark on the phantom demo's estimator model (issue 6).

Section ``fit`` of ``python -m benchmarks``. Everything runs in this one process under
``threadpoolctl.threadpool_limits(1)`` on ``sample_sequences/phantom/model.yaml`` (17 x 11 x 3 mesh, Ritz basis of
13, state 26) with one simulated measurement set of the model itself (fixed seed, 60 fps, 35 points, 120 frames:
the demo's fit window). Measured, median of repeats:

1. the baseline: one KF pass over the 120 frames (``tracker.tracking.run_kalman``);
2. ``heartcv fit``'s core, ``tracker.fit.fit`` with 1 and 3 starts (scipy ``least_squares``, central differences),
   and the fit problem's one residual evaluation (a deterministic simulation of the 120 frames plus the profiled
   offsets), with the evaluations per fit;
3. ``tracker.fit.undeformed_references`` (the reference offsets of ``track --params``);
4. the GE over the same frames (``tracker.joint.run_joint``), per step against the KF's step, and as ``heartcv track
   --params`` runs it on measured points (issue 15): with the three reference states of ``tracker.reference`` and
   the noise adaptation of ``tracker.adaptive`` (target: no slower per step than the plain GE of 2026-11-25,
   3.6 ms on the project's 2-core machine).

Each is printed with its ratio to the KF pass. The demo's wall time is dominated by rendering and measuring (see the
``render`` and ``measure`` sections); this section shows that the estimation stages cost seconds, not minutes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._harness import blas_threads, fmt_ratio, fmt_time, measure, single_threaded_blas, table

__all__ = ["bench_fit"]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "sample_sequences" / "phantom" / "model.yaml"
SEED = 0


def _setup(frames: int):
    from heartcv.tracker.io import read_model
    from heartcv.tracker.model import build_model
    from heartcv.tracker.simulate import simulate, to_measurements

    cfg = read_model(MODEL)
    model = build_model(cfg)
    sim = simulate(model, (frames - 1) / cfg.frame_rate, np.random.default_rng(SEED))
    return model, to_measurements(sim)


def bench_fit(*, quick: bool = False) -> dict:
    from heartcv.tracker.fit import FitProblem, fit, undeformed_references
    from heartcv.tracker.joint import run_joint
    from heartcv.tracker.tracking import run_kalman

    frames = 40 if quick else 120
    repeats = 2 if quick else 5
    with single_threaded_blas():
        model, meas = _setup(frames)
        print(f"model {MODEL.relative_to(REPO)}: state {model.state_dim}, {meas.n_points} points, {frames} frames at "
              f"{model.config.frame_rate:g} fps (simulated, seed {SEED}); BLAS threads: {blas_threads()}")
        theta = model.config.theta
        kf = measure(lambda: run_kalman(model, meas), repeats=repeats)
        prob = FitProblem(model, meas)
        res1 = fit(model, meas)
        res3 = fit(model, meas, np.random.default_rng(1), starts=3)
        t_res = measure(lambda: prob.residuals(theta), repeats=repeats)
        t_fit1 = measure(lambda: fit(model, meas), repeats=repeats, warmup=0)
        t_fit3 = measure(lambda: fit(model, meas, np.random.default_rng(1), starts=3), repeats=max(1, repeats // 2),
                         warmup=0)
        t_ref = measure(lambda: undeformed_references(model, meas, theta), repeats=repeats)
        t_ge = measure(lambda: run_joint(model, meas, "ge"), repeats=max(1, repeats // 2), warmup=0)
        from heartcv.tracker.adaptive import AdaptationOptions

        t_ge_track = measure(lambda: run_joint(model, meas, "ge", references="estimate",
                                               adaptation=AdaptationOptions()), repeats=max(1, repeats // 2), warmup=0)
        # per-step medians of both configurations over interleaved runs (the machine's load drifts)
        plain, tracked = [], []
        for _ in range(max(3, repeats)):
            plain.append(run_joint(model, meas, "ge").step_time[1:])
            tracked.append(run_joint(model, meas, "ge", references="estimate",
                                     adaptation=AdaptationOptions()).step_time[1:])
        ge_step = float(np.median(np.concatenate(plain)))
        ge_track_step = float(np.median(np.concatenate(tracked)))
    base = kf.median
    rows = [
        ["KF pass (baseline)", fmt_time(base), "1.00x", ""],
        ["fit residuals, one evaluation", fmt_time(t_res.median), fmt_ratio(t_res.median / base), ""],
        ["fit, 1 start", fmt_time(t_fit1.median), fmt_ratio(t_fit1.median / base),
         f"{res1.evaluations} evaluations, converged {res1.converged}"],
        ["fit, 3 starts (the demo's)", fmt_time(t_fit3.median), fmt_ratio(t_fit3.median / base),
         f"converged {res3.converged}"],
        ["undeformed references", fmt_time(t_ref.median), fmt_ratio(t_ref.median / base), ""],
        ["GE pass", fmt_time(t_ge.median), fmt_ratio(t_ge.median / base),
         f"per step {fmt_time(t_ge.median / frames)} vs KF {fmt_time(base / frames)}; step_time median "
         f"{fmt_time(ge_step)}"],
        ["GE pass, reference states + adaptation", fmt_time(t_ge_track.median), fmt_ratio(t_ge_track.median / base),
         f"per step {fmt_time(t_ge_track.median / frames)}; step_time median {fmt_time(ge_track_step)} "
         f"({ge_track_step / ge_step:.2f}x the plain GE's)"],
    ]
    print()
    print(table(["stage", "median", "/ KF pass", "note"], rows,
                title=f"Estimation stages over {frames} frames, one BLAS thread (median of repeats)"))
    print(f"fitted E = {res1.theta[3]:.6g} Pa (truth {theta[3]:.6g}), nu = {res1.theta[4]:.4f} "
          f"(truth {theta[4]:.4f}); covariance {res1.covariance_kind}")
    return {"frames": frames, "points": int(meas.n_points), "state_dim": int(model.state_dim),
            "kf_pass_s": base, "residuals_s": t_res.median, "fit_1_start_s": t_fit1.median,
            "ge_track_pass_s": t_ge_track.median, "ge_step_median_s": ge_step,
            "ge_track_step_median_s": ge_track_step,
            "fit_3_starts_s": t_fit3.median, "references_s": t_ref.median, "ge_pass_s": t_ge.median,
            "ratios": {"fit_1_start_over_kf": t_fit1.median / base, "fit_3_starts_over_kf": t_fit3.median / base,
                       "ge_over_kf": t_ge.median / base},
            "fit_evaluations": int(res1.evaluations), "theta_fit": res1.theta.tolist()}

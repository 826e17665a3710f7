"""Speed benchmarks of the patch model: build, discretisation and the Kalman-filter step.

Three sections, each a function that prints plain-text tables and returns a JSON-friendly dict:

* :func:`bench_model`      -- model build (mesh + assembly + rim elimination [+ Ritz basis]) on the paper,
  medium and fine meshes; assembly alone against scikit-fem's naive ``ElementVector`` assembly (baseline).
* :func:`bench_discretise` -- ``PatchModel.system`` per theta with the modal / expm / implicit-Euler methods
  (baseline: modal), and 21 thetas (one GE prediction's worth); single-threaded BLAS.
* :func:`bench_kf`         -- Kalman step on the paper model (``run_kalman`` step times and a bare
  ``predict`` + ``update``) against one dense 168 x 168 DGEMM (baseline); single-threaded BLAS.

Spec targets (docs/spec/model.md §2.6): paper whole build 0.17 s, medium assembly 0.31 s, fine assembly 0.71 s.
"""

from __future__ import annotations

import copy
from functools import lru_cache
from pathlib import Path
import time

import numpy as np

from ._harness import blas_info, blas_lines, blas_threads, fmt_ratio, fmt_time, measure, single_threaded_blas, table

__all__ = ["MESHES", "SPEC_S", "mesh_config", "build", "bench_model", "bench_discretise", "bench_kf"]

REPO = Path(__file__).resolve().parents[1]
PAPER_YAML = REPO / "sample_sequences" / "paper_patch.yaml"

MESHES = {
    # name: (geometry.grid, reduction section or None)
    "paper": ((9, 4, 2), None),
    "medium": ((31, 21, 4), {"modes": 10}),
    "fine": ((61, 41, 6), {"modes": 10}),
}

SPEC_S = {
    ("build", "paper"): 0.17,
    ("assembly", "medium"): 0.31,
    ("assembly", "fine"): 0.71,
}
"""Spec numbers (seconds) of docs/spec/model.md §2.6 that the measurements are compared with."""

# repeats per mesh: (whole build, assembly alone, naive ElementVector assembly)
_REPEATS = {"paper": (7, 7, 7), "medium": (3, 5, 3), "fine": (1, 3, 0)}
_QUICK_REPEATS = {"paper": (3, 3, 3), "medium": (1, 2, 1), "fine": (0, 0, 0)}


# -- configurations and models ------------------------------------------------------------------
def mesh_config(name: str):
    """The paper model file with ``geometry.grid`` (and ``reduction``) of mesh ``name``."""
    from heartcv.tracker.config import model_config_from_dict

    grid, reduction = MESHES[name]
    data = copy.deepcopy(_paper_dict())
    data["geometry"]["grid"] = list(grid)
    data.pop("reduction", None)
    if reduction is not None:
        data["reduction"] = dict(reduction)
    return model_config_from_dict(data)


@lru_cache(maxsize=1)
def _paper_dict() -> dict:
    import yaml

    with open(PAPER_YAML, encoding="utf-8") as f:
        return yaml.safe_load(f)


_MODELS: dict = {}


def build(name: str):
    """A built model of mesh ``name`` (cached for the run; the build benchmark refreshes the cache)."""
    if name not in _MODELS:
        from heartcv.tracker.model import build_model

        _MODELS[name] = build_model(mesh_config(name))
    return _MODELS[name]


def _spec_cols(kind, name, median):
    spec = SPEC_S.get((kind, name))
    if spec is None:
        return "-", "-", None
    return fmt_time(spec), fmt_ratio(median / spec), spec


# -- 1. model build and assembly ------------------------------------------------------------------
def _naive_forms():
    """scikit-fem's textbook vector-valued elasticity forms (the baseline of the assembly)."""
    from skfem import BilinearForm
    from skfem.helpers import ddot, div, dot, sym_grad

    @BilinearForm
    def k_lambda(u, v, w):
        return div(u) * div(v)

    @BilinearForm
    def k_mu(u, v, w):
        return 2.0 * ddot(sym_grad(u), sym_grad(v))

    @BilinearForm
    def mass(u, v, w):
        return dot(u, v)

    return k_lambda, k_mu, mass


def naive_assembly(mesh):
    """``K_lambda``, ``K_mu``, ``M0`` with ``ElementVector(ElementHex1())``, ``intorder=2`` (no loads)."""
    from skfem import Basis, ElementHex1, ElementVector, asm

    k_lambda, k_mu, mass = _naive_forms()
    basis = Basis(mesh.skfem_mesh(), ElementVector(ElementHex1()), intorder=2)
    return asm(k_lambda, basis), asm(k_mu, basis), asm(mass, basis)


def _rel_diff(A, B) -> float:
    return float(abs(A - B).max() / abs(B).max())


def bench_model(*, quick: bool = False) -> dict:
    from heartcv.tracker.fem import assemble
    from heartcv.tracker.geometry import build_mesh
    from heartcv.tracker.model import build_model

    reps = _QUICK_REPEATS if quick else _REPEATS
    print(f"BLAS threads in this section: {blas_threads()} (library default; the sparse LU and ARPACK work of "
          "the Ritz basis is single-threaded)")
    out = {"blas_threads": blas_threads(), "build": [], "assembly": []}

    # whole build ------------------------------------------------------------------------------
    rows = []
    for name, (grid, reduction) in MESHES.items():
        n_build = reps[name][0]
        if n_build == 0:
            continue
        cfg = mesh_config(name)
        holder = {}

        def run(cfg=cfg, holder=holder):
            holder["m"] = build_model(cfg)

        # the fine build takes tens of seconds: one cold sample, no warm-up
        t = measure(run, repeats=n_build, warmup=0 if name == "fine" else 1, number=1)
        m = holder["m"]
        _MODELS[name] = m
        spec_s, ratio_s, spec = _spec_cols("build", name, t.median)
        rows.append([name, "x".join(map(str, grid)), "full" if reduction is None else f"modes {reduction['modes']}",
                     m.mesh.n_nodes, m.free_dofs.size, m.r, m.state_dim, t.repeats, fmt_time(t.median),
                     fmt_time(t.min), spec_s, ratio_s])
        out["build"].append({"mesh": name, "grid": list(grid), "reduction": reduction, "nodes": int(m.mesh.n_nodes),
                             "free_dofs": int(m.free_dofs.size), "basis_size": int(m.r),
                             "state_dim": int(m.state_dim), "spec_s": spec,
                             "median_over_spec": t.median / spec if spec else None, **t.as_dict()})
        print(f"  built {name}: {fmt_time(t.median)}", flush=True)
    print()
    print(table(["mesh", "grid", "reduction", "nodes", "free DOF", "r", "state", "n", "median", "min", "spec",
                 "median/spec"], rows,
                title="Model build: build_model(cfg) = mesh + assembly + rim elimination [+ Ritz basis]"))
    print()

    # assembly alone vs naive ElementVector -----------------------------------------------------
    rows = []
    for name, (grid, _) in MESHES.items():
        _, n_asm, n_naive = reps[name]
        if n_asm == 0:
            continue
        geom = mesh_config(name).geometry
        t_mesh = measure(lambda geom=geom: build_mesh(geom), repeats=n_asm, warmup=1)
        mesh = build_mesh(geom)
        t_asm = measure(lambda mesh=mesh: assemble(mesh), repeats=n_asm, warmup=1, number=1)
        rec = {"mesh": name, "grid": list(grid), "elements": int(mesh.elements.shape[0]),
               "dofs": int(3 * mesh.n_nodes), "build_mesh": t_mesh.as_dict(), "assemble": t_asm.as_dict()}
        naive_s = speedup = check = None
        if n_naive:
            t_naive = measure(lambda mesh=mesh: naive_assembly(mesh), repeats=n_naive, warmup=1, number=1)
            naive_s = t_naive.median
            speedup = naive_s / t_asm.median
            fe = assemble(mesh)
            Kl, Km, M0 = naive_assembly(mesh)
            check = {"K_mu": _rel_diff(fe.K_mu, Km), "M0": _rel_diff(fe.M0, M0),
                     "K_lambda (1-pt vs 2x2x2)": _rel_diff(fe.K_lambda, Kl)}
            rec.update({"naive_element_vector": t_naive.as_dict(), "speedup_naive_over_assemble": speedup,
                        "max_rel_diff_vs_naive": check})
        spec_s, ratio_s, spec = _spec_cols("assembly", name, t_asm.median)
        rec["spec_s"] = spec
        rec["median_over_spec"] = t_asm.median / spec if spec else None
        build_rec = next((b for b in out["build"] if b["mesh"] == name), None)
        rest = None
        if build_rec is not None:
            rest = build_rec["median_s"] - t_mesh.median - t_asm.median
            rec["build_minus_mesh_and_assembly_s"] = rest
        out["assembly"].append(rec)
        rows.append([name, rec["elements"], rec["dofs"], t_asm.repeats, fmt_time(t_mesh.median),
                     fmt_time(t_asm.median), fmt_time(naive_s), fmt_ratio(speedup), spec_s, ratio_s,
                     fmt_time(rest)])
        print(f"  assembled {name}: {fmt_time(t_asm.median)}", flush=True)
    print()
    print(table(["mesh", "elements", "DOF", "n", "build_mesh", "assemble", "naive EV", "speed-up", "spec",
                 "assemble/spec", "build-rest"], rows,
                title="Assembly alone: tracker.fem.assemble(build_mesh(g)) vs naive skfem "
                      "ElementVector(ElementHex1())"))
    print("  speed-up = naive EV / assemble (baseline measured in this run; naive EV assembles only the three\n"
          "  matrices, assemble also the two load vectors). build-rest = build - build_mesh - assemble\n"
          "  (rim elimination + Ritz basis).")
    for rec in out["assembly"]:
        if "max_rel_diff_vs_naive" in rec:
            d = rec["max_rel_diff_vs_naive"]
            print(f"  check {rec['mesh']}: max rel. diff vs naive  K_mu {d['K_mu']:.1e}, M0 {d['M0']:.1e}, "
                  f"K_lambda {d['K_lambda (1-pt vs 2x2x2)']:.2f} (differs by design: 1-point rule)")
    return out


# -- 2. discretisation --------------------------------------------------------------------------
def ge_thetas(theta0, count: int = 21) -> np.ndarray:
    """``count`` deterministic parameter vectors around ``theta0`` (E x exp(+-0.5), nu in [0.35, 0.49])."""
    th = np.tile(np.asarray(theta0, float), (count, 1))
    th[:, 3] = theta0[3] * np.exp(np.linspace(-0.5, 0.5, count))
    th[:, 4] = np.roll(np.linspace(0.35, 0.49, count), count // 3)
    return th


def bench_discretise(*, quick: bool = False) -> dict:
    from heartcv.tracker.discretise import METHODS

    models = {name: build(name) for name in ("paper", "medium")}  # built outside the timed region
    repeats = 3 if quick else 11
    min_sample = 0.02 if quick else 0.1
    out = {"per_theta": [], "ge_21_thetas": []}
    with single_threaded_blas():
        print(f"BLAS threads in this section: {blas_threads()} (threadpoolctl.threadpool_limits(1))")
        out["blas_threads"] = blas_threads()
        rows = []
        for name, m in models.items():
            theta, dt = m.config.theta, m.config.dt
            ref = m.system(theta, dt, "expm").A
            base = None
            for method in METHODS:
                t = measure(lambda m=m, method=method, theta=theta, dt=dt: m.system(theta, dt, method), repeats=repeats,
                            warmup=1,
                            min_sample_s=min_sample)
                if method == "modal":
                    base = t.median
                A = m.system(theta, dt, method).A
                err = float(np.abs(A - ref).max())
                rho = float(np.abs(np.linalg.eigvals(A)).max())
                rows.append([name, m.state_dim, method, t.repeats, t.number, fmt_time(t.median), fmt_time(t.min),
                             fmt_ratio(t.median / base), f"{rho:.2e}", f"{err:.1e}"])
                out["per_theta"].append({"model": name, "state_dim": int(m.state_dim), "method": method,
                                         "ratio_to_modal": t.median / base, "max_abs_A_minus_expm": err,
                                         "spectral_radius_A": rho, **t.as_dict()})
        print(table(["model", "state", "method", "n", "calls", "median", "min", "vs modal", "rho(A)",
                     "max|A-A_expm|"], rows,
                    title="Discretisation per theta: PatchModel.system(theta, dt, method), dt = 1/frame_rate"))
        print("  vs modal = median / modal median (baseline). rho(A) = spectral radius; max|A-A_expm| = largest\n"
              "  entry difference to the expm oracle (implicit Euler is first order, so it differs at 30 Hz).")
        for name in models:
            r = {x["method"]: x["median_s"] for x in out["per_theta"] if x["model"] == name}
            print(f"  {name}: expm/modal = {r['expm'] / r['modal']:.2f}, "
                  f"implicit-euler/modal = {r['implicit-euler'] / r['modal']:.2f}")
        print()

        rows = []
        for name, m in models.items():
            thetas = ge_thetas(m.config.theta, 21)
            method = m.config.method

            def run(m=m, thetas=thetas):
                for th in thetas:
                    m.system(th)

            t = measure(run, repeats=repeats, warmup=1, min_sample_s=min_sample)
            single = next(x["median_s"] for x in out["per_theta"] if x["model"] == name and x["method"] == method)
            rows.append([name, m.state_dim, method, t.repeats, fmt_time(t.median), fmt_time(t.median / 21),
                         fmt_ratio(t.median / (21 * single))])
            out["ge_21_thetas"].append({"model": name, "state_dim": int(m.state_dim), "method": method,
                                        "per_theta_s": t.median / 21, "ratio_to_21_single": t.median / (21 * single),
                                        **t.as_dict()})
        print(table(["model", "state", "method", "n", "21 thetas", "per theta", "vs 21 x single"], rows,
                    title="A for 21 thetas (one GE prediction), configured method, single-threaded"))
    return out


# -- 3. Kalman step -----------------------------------------------------------------------------
def _measurement_set(sim):
    """Patch-frame MeasurementSet of a simulation (as ``heartcv model simulate`` writes it)."""
    from heartcv.tracker.simulate import to_measurements

    return to_measurements(sim, {"producer": "benchmarks"})


def bench_kf(*, quick: bool = False) -> dict:
    from heartcv.tracker.kalman import GaussianState, predict, update, update_blocks
    from heartcv.tracker.simulate import simulate
    from heartcv.tracker.tracking import locate_points, run_kalman

    model = build("paper")
    n = model.state_dim
    runs = 2 if quick else 3
    repeats = 5 if quick else 11
    min_sample = 0.02 if quick else 0.1
    out = {}
    with single_threaded_blas():
        print(f"BLAS threads in this section: {blas_threads()} (threadpoolctl.threadpool_limits(1))")
        out["blas_threads"] = blas_threads()
        t0 = time.perf_counter()
        sim = simulate(model, 10.0, np.random.default_rng(0))
        t_sim = time.perf_counter() - t0
        meas = _measurement_set(sim)
        K = meas.n_frames

        # run_kalman: per-step times recorded by the filter itself (step 0 is an update only)
        run_kalman(model, meas)  # warm-up
        steps, walls = [], []
        for _ in range(runs):
            t0 = time.perf_counter()
            est = run_kalman(model, meas)
            walls.append(time.perf_counter() - t0)
            steps.append(np.asarray(est.step_time)[1:])
        steps = np.concatenate(steps)
        kf_step = float(np.median(steps))

        # bare predict + update at a settled covariance
        theta, dt = model.config.theta, model.config.dt
        pts = locate_points(model, meas)
        H = pts.observation.H
        sysd = model.system(theta, dt)
        Q = model.process_noise(theta, dt)
        u = meas.input_columns(model.input_names)
        y_all = meas.positions[:, pts.keep, :].reshape(K, -1)
        R = np.eye(H.shape[0]) * sim.measurement_std**2
        trans = meas.translation()
        ref = pts.observation.reference

        def off(j):
            return (ref + trans[j]).reshape(-1)

        k = K // 2
        state = GaussianState(model.static_state(theta, u[0]), model.initial_covariance())
        state = update(state, y_all[0], H, R, off(0)).state
        for j in range(1, k):  # the filter up to frame k - 1, so the covariance has settled (not timed)
            state = update(predict(state, sysd.A, Q, sysd.B0 @ u[j - 1] + sysd.B1 @ u[j]), y_all[j], H, R,
                           off(j)).state
        b = sysd.B0 @ u[k - 1] + sysd.B1 @ u[k]
        offset = off(k)
        pred = predict(state, sysd.A, Q, b)
        t_pu = measure(lambda: update(predict(state, sysd.A, Q, b), y_all[k], H, R, offset), repeats=repeats,
                       min_sample_s=min_sample)
        t_p = measure(lambda: predict(state, sysd.A, Q, b), repeats=repeats, min_sample_s=min_sample)
        t_u = measure(lambda: update(pred, y_all[k], H, R, offset), repeats=repeats, min_sample_s=min_sample)

        # baseline: one dense n x n DGEMM
        rng = np.random.default_rng(1)
        a, bm = rng.standard_normal((n, n)), rng.standard_normal((n, n))
        c = np.empty((n, n))
        t_mm = measure(lambda: np.matmul(a, bm, out=c), repeats=repeats, min_sample_s=min_sample)
        gflops = 2.0 * n**3 / t_mm.median / 1e9

        # many points per frame (dense measurements): the low-rank block update against the dense Cholesky form,
        # on the settled state of the paper model, random SPD 3 x 3 blocks and random rows (only the cost matters)
        many = []
        for p in ((50, 300) if quick else (50, 300, 1000)):
            Hp = rng.standard_normal((3 * p, n))
            Bp = rng.standard_normal((p, 3, 3))
            blocks = Bp @ np.swapaxes(Bp, 1, 2) + 0.1 * np.eye(3)
            Rp = np.zeros((p, 3, p, 3))
            Rp[np.arange(p), :, np.arange(p), :] = blocks
            Rp = Rp.reshape(3 * p, 3 * p)
            yp = rng.standard_normal(3 * p)
            reps = repeats if p <= 300 else 3
            t_dense = measure(lambda: update(pred, yp, Hp, Rp), repeats=reps, min_sample_s=min_sample)
            t_block = measure(lambda: update_blocks(pred, yp, Hp, blocks), repeats=reps, min_sample_s=min_sample)
            many.append((p, t_dense, t_block))

    rows = [
        [f"run_kalman step (median of {steps.size} steps)", fmt_time(kf_step), "-", fmt_ratio(kf_step / t_mm.median)],
        ["run_kalman wall / frame", fmt_time(float(np.median(walls)) / K), "-",
         fmt_ratio(float(np.median(walls)) / K / t_mm.median)],
        ["bare predict + update", fmt_time(t_pu.median), fmt_time(t_pu.min), fmt_ratio(t_pu.median / t_mm.median)],
        ["  predict", fmt_time(t_p.median), fmt_time(t_p.min), fmt_ratio(t_p.median / t_mm.median)],
        ["  update", fmt_time(t_u.median), fmt_time(t_u.min), fmt_ratio(t_u.median / t_mm.median)],
        [f"DGEMM {n}x{n} (baseline)", fmt_time(t_mm.median), fmt_time(t_mm.min), "1.00x"],
    ]
    print(f"Paper model: state {n}, {pts.observation.n_points} points ({H.shape[0]} rows), {K} frames "
          f"(10 s at {model.config.frame_rate:g} Hz; simulated in {fmt_time(t_sim)})")
    print(table(["KF", "median", "min", "/ DGEMM"], rows,
                title="Kalman step on the paper model, single-threaded"))
    print(f"  KF step / DGEMM = {kf_step / t_mm.median:.2f}   (bare predict+update / DGEMM = "
          f"{t_pu.median / t_mm.median:.2f});  DGEMM {n}x{n}: {gflops:.2f} GFLOP/s (1 thread)")
    print(table(["points (rows)", "update (dense S)", "update_blocks", "dense / blocks"],
                [[f"{p} ({3 * p})", fmt_time(d.median), fmt_time(b.median), fmt_ratio(d.median / b.median)]
                 for p, d, b in many],
                title=f"Update with many points, state {n}: S never formed (kalman.update_blocks), single-threaded"))
    out["many_points_update"] = [{"points": p, "rows": 3 * p, "dense": d.as_dict(), "blocks": b.as_dict(),
                                  "dense_over_blocks": d.median / b.median} for p, d, b in many]
    out.update({
        "state_dim": int(n), "frames": int(K), "observed_rows": int(H.shape[0]), "simulate_s": t_sim,
        "run_kalman_step_median_s": kf_step, "run_kalman_step_p90_s": float(np.percentile(steps, 90)),
        "run_kalman_wall_s": walls, "bare_predict_update": t_pu.as_dict(), "predict": t_p.as_dict(),
        "update": t_u.as_dict(), "dgemm": t_mm.as_dict(), "dgemm_gflops": gflops,
        "kf_step_over_dgemm": kf_step / t_mm.median, "bare_step_over_dgemm": t_pu.median / t_mm.median,
    })
    return out


SECTIONS = {"model": bench_model, "discretise": bench_discretise, "kf": bench_kf}


def blas_report() -> tuple[list, list[str]]:
    info = blas_info()
    return info, blas_lines(info)

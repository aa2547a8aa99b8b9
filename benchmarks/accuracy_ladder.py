"""What accuracy costs in time: every jaxlens method and setting against exact answers.

Every method of `jaxlens.trace` (the original C++ program's semi-implicit Euler with
dphi = 0.003, RK4 at several steps, adaptive Dormand-Prince 5(4) at several tolerances,
the exact elliptic form at 3 ... 8 duplication steps, the alpha-table `RayMap`) in
float64 and float32, and three peers in the same run (scipy `solve_ivp` DOP853 per
ray with events, as the Python program jaxlens grew from; diffrax Tsit5, vmapped,
with an event root find; a plain NumPy vectorised loop of the Euler scheme), on the
same three ray sets (see `_common.ray_sets`). Errors are |phi - phi_exact| in radians
over rays that escape in both, against `Exact(iterations=12)` in float64 on the same
(rounded) rays, itself cross-checked against mpmath quadrature.

Writes `results/accuracy_ladder.csv`, `results/accuracy_ladder.md` and
`results/pareto.png`.

    python benchmarks/accuracy_ladder.py [--quick] [--rays N]
"""

import argparse
import csv
import math
import time

import jax.numpy as jnp
from _common import (
    CAPTURED,
    ESCAPED,
    RESULTS,
    UNRESOLVED,
    error_stats,
    fmt,
    jax,
    jaxlens,
    load_average,
    machine,
    machine_markdown,
    markdown_table,
    np,
    phi_mpmath,
    ray_sets,
    reference,
    time_call,
)

MAX_WINDINGS = 10.0


def jaxlens_methods(quick: bool):
    """(family, setting label, setting value, method) for every jaxlens setting."""
    rk4 = (0.1, 0.03, 0.01) if quick else (0.1, 0.03, 0.01, 0.003)
    tols = (1e-6, 1e-9, 1e-12) if quick else (1e-6, 1e-8, 1e-10, 1e-12)
    out = [("euler", "dphi=0.003", 0.003, jaxlens.Euler(dphi=0.003))]
    out += [("rk4", f"dphi={h:g}", h, jaxlens.RK4(dphi=h)) for h in rk4]
    out += [("dopri5", f"tol={t:g}", t, jaxlens.DormandPrince(tol=t)) for t in tols]
    out += [("exact", f"iterations={n}", n, jaxlens.Exact(iterations=n)) for n in range(3, 9)]
    return out


def row(family, setting, value, dtype, set_name, n, stats, rate, compile_s, setup_s=None, note=""):
    """One line of the results table."""
    return {
        "family": family,
        "setting": setting,
        "value": value,
        "dtype": dtype,
        "set": set_name,
        "n_rays": n,
        "median_err": stats["median"],
        "max_err": stats["max"],
        "max_err_wc": stats["max_wc"],
        "max_err_far": stats["max_far"],
        "status_agree": stats["agree"],
        "n_escaped": stats["n_esc"],
        "rays_per_s": rate,
        "compile_s": compile_s,
        "setup_s": setup_s,
        "note": note,
    }


# ---------------------------------------------------------------------------
# jaxlens methods


def run_jaxlens(sets, refs, dtypes, quick):
    """Every setting of every integrator and of the exact form, on every set."""
    rows = []
    for family, setting, value, method in jaxlens_methods(quick):
        for dtype in dtypes:

            @jax.jit
            def f(alpha, distance, method=method):
                r = jaxlens.trace(alpha, distance, method=method, max_windings=MAX_WINDINGS)
                return r.phi, r.status

            compiled, compile_s = None, None
            for name, s in sets.items():
                a = s["alpha"].astype(dtype)
                d = s["distance"].astype(dtype)
                if compiled is None:  # one shape for all sets: one compilation
                    t = time.perf_counter()
                    compiled = f.lower(a, d).compile()
                    compile_s = time.perf_counter() - t
                _, run_s, (phi, status) = time_call(compiled, a, d)
                ref_phi, ref_status = refs[dtype][name]
                stats = error_stats(phi, status, ref_phi, ref_status, s["delta"])
                rows.append(
                    row(
                        family,
                        setting,
                        value,
                        dtype,
                        name,
                        a.size,
                        stats,
                        a.size / run_s,
                        compile_s,
                    )
                )
                print(_progress(rows[-1]), flush=True)
    return rows


def _table_trace_available():
    """Whether `trace(..., method="table")` exists yet."""
    try:
        jaxlens.trace(np.array([0.3]), 20.0, method="table")
        return True
    except (ValueError, TypeError, NotImplementedError):
        return False


def run_table(sets, refs, dtypes, accuracies):
    """The alpha-table: one `RayMap` per camera distance, then interpolation.

    Build time (per distance, after compilation) goes in `setup_s`; `rays_per_s` is the
    evaluation alone, the cost a render pays per pixel.
    """
    rows = []
    if not hasattr(jaxlens, "RayMap"):
        print("jaxlens.RayMap does not exist yet: table method skipped", flush=True)
        return rows, "jaxlens.RayMap not available: the table method was skipped."
    use_trace = _table_trace_available()
    notes = []
    if not use_trace:
        notes.append(
            "`trace(..., method='table')` is not available yet; the table is measured "
            "through `jaxlens.RayMap` directly."
        )
    for acc in accuracies:
        for dtype in dtypes:
            build = jax.jit(lambda d, acc=acc: jaxlens.RayMap.build(d, accuracy=acc))
            evaluate = jax.jit(lambda rm, a: (lambda r: (r.phi, r.status))(rm(a)))
            build_compile = None
            for name, s in sets.items():
                a_all = s["alpha"].astype(dtype)
                d_all = s["distance"].astype(dtype)
                phi = np.zeros(a_all.shape, np.float64)
                status = np.zeros(a_all.shape, np.int8)
                run_total, builds, eval_compile, cache = 0.0, [], 0.0, {}
                for d in np.unique(d_all):
                    idx = np.nonzero(d_all == d)[0]
                    dd = np.asarray(d, dtype)
                    if build_compile is None:
                        t = time.perf_counter()
                        build_c = build.lower(dd).compile()
                        build_compile = time.perf_counter() - t
                    _, b_s, rm = time_call(build_c, dd, target_s=0.3, min_repeats=2)
                    builds.append(b_s)
                    if idx.size not in cache:  # one compilation per batch shape
                        t = time.perf_counter()
                        cache[idx.size] = evaluate.lower(rm, a_all[idx]).compile()
                        eval_compile += time.perf_counter() - t
                    _, r_s, (p, st) = time_call(cache[idx.size], rm, a_all[idx], target_s=0.5)
                    run_total += r_s
                    phi[idx], status[idx] = np.asarray(p), np.asarray(st)
                ref_phi, ref_status = refs[dtype][name]
                stats = error_stats(phi, status, ref_phi, ref_status, s["delta"])
                r = row(
                    "table",
                    f"RayMap accuracy={acc:g}",
                    acc,
                    dtype,
                    name,
                    a_all.size,
                    stats,
                    a_all.size / run_total,
                    build_compile + eval_compile,
                    float(np.median(builds)),
                    note=f"knots={int(rm.phi.shape[0])}",
                )
                rows.append(r)
                print(_progress(r), flush=True)
    if use_trace:
        rows += run_trace_table(sets, refs, dtypes, accuracies)
    return rows, " ".join(notes)


def run_trace_table(sets, refs, dtypes, accuracies):
    """`trace(..., method="table")` per camera distance: a build inside every call.

    This is what a caller gets from `trace` on a batch with one distance; the rate
    includes building the table, so it depends on the batch size (here, the rays of one
    distance in the set).
    """
    rows = []
    for acc in accuracies:
        for dtype in dtypes:
            f = jax.jit(
                lambda a, d, acc=acc: (lambda r: (r.phi, r.status))(
                    jaxlens.trace(a, d, method="table", accuracy=acc)
                )
            )
            for name, s in sets.items():
                a_all = s["alpha"].astype(dtype)
                d_all = s["distance"].astype(dtype)
                phi = np.zeros(a_all.shape, np.float64)
                status = np.zeros(a_all.shape, np.int8)
                run_total, compile_s, cache = 0.0, 0.0, {}
                for d in np.unique(d_all):
                    idx = np.nonzero(d_all == d)[0]
                    dd = np.asarray(d, dtype)
                    if idx.size not in cache:  # one compilation per batch shape
                        t = time.perf_counter()
                        cache[idx.size] = f.lower(a_all[idx], dd).compile()
                        compile_s += time.perf_counter() - t
                    _, r_s, (p, st) = time_call(cache[idx.size], a_all[idx], dd, target_s=0.5)
                    run_total += r_s
                    phi[idx], status[idx] = np.asarray(p), np.asarray(st)
                ref_phi, ref_status = refs[dtype][name]
                stats = error_stats(phi, status, ref_phi, ref_status, s["delta"])
                n_d = len(np.unique(d_all))
                r = row(
                    "table",
                    f"trace(method='table') accuracy={acc:g}",
                    acc,
                    dtype,
                    name,
                    a_all.size,
                    stats,
                    a_all.size / run_total,
                    compile_s,
                    note=f"build included; {a_all.size // n_d} rays per distance",
                )
                rows.append(r)
                print(_progress(r), flush=True)
    return rows


# ---------------------------------------------------------------------------
# Peers


def initial_state(alpha, distance):
    """$u_0 = 1/D$ and $du/d\\phi(0) = u_0 \\sqrt{1 - u_0} \\cot\\alpha$ (PHYSICS.md), NumPy."""
    u0 = 1.0 / distance
    v0 = u0 * np.sqrt((distance - 1.0) / distance) * np.cos(alpha) / np.abs(np.sin(alpha))
    return u0, v0


def scipy_one(alpha, distance, rtol=1e-10, atol=1e-12):
    """One ray with scipy `solve_ivp` (DOP853), events at u = 0 and u = 1: (phi, status)."""
    from scipy.integrate import solve_ivp

    u0, v0 = initial_state(alpha, distance)

    def rhs(phi, y):
        return (y[1], 1.5 * y[0] * y[0] - y[0])

    def out(phi, y):
        return y[0]

    def horizon(phi, y):
        return 1.0 - y[0]

    out.terminal = horizon.terminal = True
    out.direction = horizon.direction = -1
    sol = solve_ivp(
        rhs,
        (0.0, 2 * math.pi * MAX_WINDINGS),
        (u0, v0),
        method="DOP853",
        rtol=rtol,
        atol=atol,
        events=(out, horizon),
    )
    if sol.t_events[0].size:
        return sol.t_events[0][0], ESCAPED
    if sol.t_events[1].size:
        return sol.t_events[1][0], CAPTURED
    return sol.t[-1], UNRESOLVED


def run_scipy(sets, refs, n_sub):
    """scipy solve_ivp per ray on the first `n_sub` rays of each set; rate scaled from them."""
    rows = []
    scipy_one(0.3, 20.0)  # import and warm up
    for name, s in sets.items():
        a, d = s["alpha"][:n_sub], s["distance"][:n_sub]
        t = time.perf_counter()
        res = [scipy_one(x, y) for x, y in zip(a, d)]
        run_s = time.perf_counter() - t
        phi = np.array([r[0] for r in res])
        status = np.array([r[1] for r in res], np.int8)
        ref_phi, ref_status = (x[:n_sub] for x in refs["float64"][name])
        stats = error_stats(phi, status, ref_phi, ref_status, s["delta"][:n_sub])
        rows.append(
            row(
                "scipy",
                "solve_ivp DOP853 rtol=1e-10 atol=1e-12",
                1e-10,
                "float64",
                name,
                n_sub,
                stats,
                n_sub / run_s,
                None,
                note="per ray, Python loop",
            )
        )
        print(_progress(rows[-1]), flush=True)
    return rows


def run_diffrax(sets, refs, n_sub, rtol=1e-10, atol=1e-12):
    """diffrax Tsit5 with a PID controller, vmapped, event at u = 0 / u = 1 with Newton."""
    import diffrax
    import optimistix as optx

    term = diffrax.ODETerm(lambda t, y, args: (y[1], 1.5 * y[0] ** 2 - y[0]))
    event = diffrax.Event(
        (lambda t, y, args, **kw: y[0], lambda t, y, args, **kw: 1.0 - y[0]),
        root_finder=optx.Newton(rtol=1e-12, atol=1e-14),
    )

    def one(alpha, distance):
        u0 = 1.0 / distance
        v0 = u0 * jnp.sqrt((distance - 1.0) / distance) * jnp.cos(alpha) / jnp.abs(jnp.sin(alpha))
        sol = diffrax.diffeqsolve(
            term,
            diffrax.Tsit5(),
            0.0,
            2 * math.pi * MAX_WINDINGS,
            0.01,
            (u0, v0),
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
            event=event,
            saveat=diffrax.SaveAt(t1=True),
            max_steps=100_000,
            throw=False,
        )
        esc, cap = sol.event_mask
        return sol.ts[-1], jnp.where(esc, ESCAPED, jnp.where(cap, CAPTURED, UNRESOLVED))

    f = jax.jit(jax.vmap(one))
    rows, compiled, compile_s = [], None, None
    for name, s in sets.items():
        a, d = s["alpha"][:n_sub], s["distance"][:n_sub]
        if compiled is None:
            t = time.perf_counter()
            compiled = f.lower(a, d).compile()
            compile_s = time.perf_counter() - t
        _, run_s, (phi, status) = time_call(compiled, a, d)
        ref_phi, ref_status = (x[:n_sub] for x in refs["float64"][name])
        stats = error_stats(phi, status, ref_phi, ref_status, s["delta"][:n_sub])
        rows.append(
            row(
                "diffrax",
                f"Tsit5 rtol={rtol:g} atol={atol:g}",
                rtol,
                "float64",
                name,
                n_sub,
                stats,
                n_sub / run_s,
                compile_s,
                note="vmap, Event + Newton",
            )
        )
        print(_progress(rows[-1]), flush=True)
    return rows


def numpy_euler(alpha, distance, dphi=0.003, max_steps=50_000):
    """The original program's loop in plain NumPy: semi-implicit Euler, all rays at once.

    Finished rays drop out of the working set; the crossing of u = 0 (or u = 1) is
    placed by linear interpolation within the last step.

    **Returns:** `(phi, status)` (radians; `ESCAPED` / `CAPTURED` / `UNRESOLVED`).
    """
    u, v = initial_state(np.asarray(alpha, np.float64), np.asarray(distance, np.float64))
    n = u.size
    phi = np.zeros(n)
    status = np.full(n, UNRESOLVED, np.int8)
    live = np.arange(n)
    uu, vv = u.copy(), v.copy()
    for k in range(max_steps):
        if live.size == 0:
            break
        vv = vv + dphi * (1.5 * uu * uu - uu)
        un = uu + dphi * vv
        out, cap = un <= 0.0, un >= 1.0
        done = out | cap
        if done.any():
            target = np.where(out, 0.0, 1.0)[done]
            frac = (uu[done] - target) / (uu[done] - un[done])
            idx = live[done]
            phi[idx] = k * dphi + frac * dphi
            status[idx] = np.where(out[done], ESCAPED, CAPTURED)
            keep = ~done
            live, uu, vv = live[keep], un[keep], vv[keep]
        else:
            uu = un
    return phi, status


def run_numpy(sets, refs, n_sub):
    """The NumPy Euler loop on the first `n_sub` rays of each set."""
    rows = []
    for name, s in sets.items():
        a, d = s["alpha"][:n_sub], s["distance"][:n_sub]
        first, run_s, (phi, status) = time_call(numpy_euler, a, d, target_s=0.0, min_repeats=1)
        run_s = min(first, run_s)
        ref_phi, ref_status = (x[:n_sub] for x in refs["float64"][name])
        stats = error_stats(phi, status, ref_phi, ref_status, s["delta"][:n_sub])
        rows.append(
            row(
                "numpy",
                "Euler dphi=0.003",
                0.003,
                "float64",
                name,
                n_sub,
                stats,
                n_sub / run_s,
                None,
                note="vectorised loop",
            )
        )
        print(_progress(rows[-1]), flush=True)
    return rows


# ---------------------------------------------------------------------------
# The reference, checked


def cross_check(sets, n_check):
    """`Exact(iterations=12)` against mpmath quadrature on `n_check` rays of each set.

    **Returns:** `{set: (n, max |diff|, max |diff| * |delta|, max over |delta| >= 1e-5)}`.
    """
    out = {}
    for name, s in sets.items():
        idx = np.linspace(0, s["alpha"].size - 1, n_check).astype(int)
        ref_phi, ref_status = reference(s["alpha"][idx], s["distance"][idx])
        diffs, scaled, wc, mismatch = [], [], [], 0
        for i, j in enumerate(idx):
            p = phi_mpmath(s["alpha"][j], s["distance"][j])
            if (p is None) != (ref_status[i] != ESCAPED):
                mismatch += 1
                continue
            if p is None:
                continue
            e = abs(p - ref_phi[i])
            diffs.append(e)
            scaled.append(e * abs(s["delta"][j]))
            if abs(s["delta"][j]) >= 1e-5:
                wc.append(e)
        out[name] = {
            "n": len(diffs),
            "max": max(diffs),
            "max_times_delta": max(scaled),
            "max_wc": max(wc) if wc else float("nan"),
            "status_mismatch": mismatch,
        }
        print(f"cross-check {name}: {out[name]}", flush=True)
    return out


# ---------------------------------------------------------------------------
# Outputs


def _progress(r):
    return (
        f"{r['family']:8s} {r['setting']:38s} {r['dtype']:8s} {r['set']:14s} "
        f"median {fmt(r['median_err'])}  max {fmt(r['max_err'])}  max_wc {fmt(r['max_err_wc'])}  "
        f"agree {r['status_agree']:.4f}  {r['rays_per_s']:.3g} rays/s"
    )


TARGETS = (1e-3, 1e-6, 1e-9, 1e-12)


def recommendations(rows):
    """Ladder constants from the measured float64 errors.

    - RK4 and Dormand-Prince: per ray set, the largest ratio of the max error over
      well-conditioned rays to $h^4$ (resp. to `tol`), over the settings whose error
      is above round-off.
    - Exact: the fewest duplication steps whose max error meets each target, judged
      on all escaping rays (`Exact(n)` and the reference share every rounding but the
      $R_F$ truncation, so the truncation error shows even next to the shadow edge)
      and on well-conditioned rays.
    - Fastest: per target, the fastest float64 method (its slowest set) whose max
      error on well-conditioned rays meets the target on every set, with statuses
      agreeing on >= 99.9 % of the rays of every set.
    """
    f64 = [r for r in rows if r["dtype"] == "float64"]
    sets = list(dict.fromkeys(r["set"] for r in f64))
    rec = {"rk4": {}, "dopri5": {}, "rk4_far": {}, "dopri5_far": {}}
    for family, power in (("rk4", 4), ("dopri5", 1)):
        for set_name in sets:
            for key, col in ((family, "max_err_wc"), (family + "_far", "max_err_far")):
                ratios = [
                    r[col] / r["value"] ** power
                    for r in f64
                    if r["family"] == family and r["set"] == set_name and r[col] > 1e-12
                ]
                rec[key][set_name] = max(ratios) if ratios else float("nan")
    worst = {}
    for r in f64:
        w = worst.setdefault(
            (r["family"], r["setting"]),
            {"value": r["value"], "err": 0.0, "err_all": 0.0, "rate": math.inf, "agree": 1.0},
        )
        for key, col in (("err", "max_err_wc"), ("err_all", "max_err")):
            if np.isfinite(r[col]):
                w[key] = max(w[key], r[col])
        w["rate"] = min(w["rate"], r["rays_per_s"])
        w["agree"] = min(w["agree"], r["status_agree"])
    rec["exact_all"], rec["exact_wc"], rec["fastest"] = {}, {}, {}
    for acc in TARGETS:
        for key, col in (("exact_all", "err_all"), ("exact_wc", "err")):
            ok = sorted(
                w["value"]
                for (fam, _), w in worst.items()
                if fam == "exact" and w[col] <= acc and w["agree"] == 1.0
            )
            rec[key][acc] = ok[0] if ok else None
        cands = [
            (w["rate"], k) for k, w in worst.items() if w["err"] <= acc and w["agree"] >= 0.999
        ]
        rec["fastest"][acc] = max(cands) if cands else None
    rec["worst"] = worst
    return rec


def write_csv(rows, path):
    """All rows as CSV."""
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def write_markdown(rows, rec, check, info, args, notes, path):
    """The table a reader looks at, with the machine and the ladder recommendations."""
    lines = [
        "# Accuracy ladder: error against exact vs rays per second\n",
        machine_markdown(info),
        f"- Rays: {args.rays} per set for jaxlens (each set at once, one batch); scipy on "
        f"the first {args.scipy_rays} rays of each set, diffrax on {args.diffrax_rays}, "
        f"NumPy on {args.numpy_rays}. Command: `python benchmarks/accuracy_ladder.py"
        f"{' --quick' if args.quick else ''}`.\n",
        "- Errors: |phi - phi_exact| (rad) over rays that escape in both, against "
        "`Exact(iterations=12)` in float64 for the same (rounded) rays. `max wc`: max over "
        "well-conditioned rays, |delta| >= 1e-5 from the shadow edge (the moderate set, "
        "uniform in alpha, also has rays within 1e-4 of the edge); near the edge the "
        "escape angle changes by "
        "~eps/|delta| when the ray angle is rounded, a floor no method beats. `agree`: "
        "fraction of rays with the same escaped / captured / unresolved status. "
        "`max far`: max over rays with |delta| >= 1e-2.\n",
        "- Rays/s: median of repeats after a warm-up, `block_until_ready()`; compile "
        "(tracing + XLA) apart. For the table, `setup` is the build of one RayMap "
        "(per distance) and rays/s the interpolation alone.\n",
    ]
    if notes:
        lines.append(f"- {notes}\n")
    lines.append("\n## Reference cross-check (Exact(12) vs mpmath quadrature)\n\n")
    lines.append(
        markdown_table(
            ["set", "rays", "max diff", "max diff, abs(delta) >= 1e-5", "max diff x abs(delta)"],
            [
                [k, v["n"], fmt(v["max"]), fmt(v["max_wc"]), fmt(v["max_times_delta"])]
                for k, v in check.items()
            ],
        )
    )
    lines.append("\n## Ladder from these figures (float64)\n\n")
    lines.append(
        "Error coefficients: max error / dphi^4 (RK4) and / tol (Dormand-Prince), the "
        "largest over the settings measured above round-off; *wc*: rays with |delta| >= "
        "1e-5, *far*: rays with |delta| >= 1e-2 (away from the shadow edge; integration "
        "errors grow about as 1/|delta| towards it, since nearby orbits diverge like "
        "e^phi around the photon sphere).\n\n"
    )
    lines.append(
        markdown_table(
            [
                "set",
                "RK4 err/dphi^4, wc",
                "RK4 err/dphi^4, far",
                "DOPRI err/tol, wc",
                "DOPRI err/tol, far",
            ],
            [
                [
                    k,
                    fmt(rec["rk4"][k]),
                    fmt(rec["rk4_far"][k]),
                    fmt(rec["dopri5"][k]),
                    fmt(rec["dopri5_far"][k]),
                ]
                for k in rec["rk4"]
            ],
        )
    )
    far, mod = rec["dopri5_far"].get("far camera"), rec["dopri5_far"].get("moderate")
    if far and mod and np.isfinite(far) and np.isfinite(mod) and far > 30 * mod:
        lines.append(
            f"\nNote: Dormand-Prince's error/tol on the far-camera set ({far:.3g}) is "
            f"{far / mod:.0f}x the moderate one: there u ~ 1/D is tiny, so an absolute "
            "tolerance on u accepts ever larger steps. This is a defect of the error norm "
            "(a relative norm or a step cap fixes it), not a coefficient for the ladder.\n"
        )
    lines.append("\n")
    lines.append(
        markdown_table(
            [
                "accuracy (rad)",
                "fewest Exact iterations, all rays",
                "fewest Exact iterations, well-conditioned",
                "fastest float64 method meeting it (wc rays, every set)",
                "its rays/s (slowest set)",
            ],
            [
                [
                    f"{acc:g}",
                    rec["exact_all"][acc] if rec["exact_all"][acc] is not None else "none",
                    rec["exact_wc"][acc] if rec["exact_wc"][acc] is not None else "none",
                    " ".join(rec["fastest"][acc][1]) if rec["fastest"][acc] else "none",
                    fmt(rec["fastest"][acc][0]) if rec["fastest"][acc] else "-",
                ]
                for acc in TARGETS
            ],
        )
    )
    header = [
        "method",
        "setting",
        "dtype",
        "median err",
        "max err",
        "max wc",
        "max far",
        "agree",
        "rays/s",
        "compile s",
        "setup s",
    ]
    for set_name in dict.fromkeys(r["set"] for r in rows):
        lines.append(f"\n## {set_name}\n\n")
        body = [
            [
                r["family"],
                r["setting"],
                r["dtype"],
                fmt(r["median_err"]),
                fmt(r["max_err"]),
                fmt(r["max_err_wc"]),
                fmt(r["max_err_far"]),
                f"{r['status_agree']:.4f}",
                fmt(r["rays_per_s"]),
                f"{r['compile_s']:.2f}" if r["compile_s"] is not None else "-",
                fmt(r["setup_s"]) if r["setup_s"] is not None else "-",
            ]
            for r in rows
            if r["set"] == set_name
        ]
        lines.append(markdown_table(header, body))
    lines.append("\n![Pareto plot](pareto.png)\n")
    path.write_text("".join(lines))


_STYLE = {
    "euler": ("tab:red", "v"),
    "rk4": ("tab:orange", "s"),
    "dopri5": ("tab:green", "D"),
    "exact": ("tab:blue", "o"),
    "table": ("tab:purple", "*"),
    "scipy": ("black", "X"),
    "diffrax": ("tab:brown", "P"),
    "numpy": ("tab:gray", "^"),
}


def _short(r):
    """A short label for a plot point: family and the number that sets it."""
    setting = r["setting"]
    if r["family"] == "table":
        return ("trace table " if setting.startswith("trace") else "RayMap ") + setting.split("=")[
            -1
        ]
    if r["family"] in ("scipy", "diffrax", "numpy"):
        return r["family"]
    return f"{r['family']} {setting.split('=')[-1]}"


def read_csv(path):
    """Rows of a results CSV, numbers parsed."""
    rows = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            for k in r:
                if k in ("family", "setting", "dtype", "set", "note"):
                    continue
                r[k] = None if r[k] in ("", "None") else float(r[k])
            rows.append(r)
    return rows


def pareto_plot(rows, path):
    """Log-log max error (well-conditioned rays) vs rays/s, one panel per ray set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(dict.fromkeys(r["set"] for r in rows))
    fig, axes = plt.subplots(1, len(sets), figsize=(6.5 * len(sets), 6.0), squeeze=False)
    for ax, set_name in zip(axes[0], sets):
        for r in rows:
            if r["set"] != set_name:
                continue
            color, marker = _STYLE.get(r["family"], ("k", "o"))
            err = max(r["max_err_wc"], 1e-17) if np.isfinite(r["max_err_wc"]) else 1.0
            face = color if r["dtype"] == "float64" else "none"
            ax.scatter(r["rays_per_s"], err, marker=marker, s=55, edgecolors=color, facecolors=face)
            if r["dtype"] == "float64":  # float32 points: open markers, unlabelled
                ax.annotate(
                    _short(r),
                    (r["rays_per_s"], err),
                    fontsize=6,
                    xytext=(3, 2),
                    textcoords="offset points",
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("rays per second (this machine)")
        ax.set_ylabel("max |phi - phi_exact| (rad), well-conditioned rays")
        ax.set_title(set_name)
        ax.grid(True, which="major", alpha=0.3)
    handles = [
        plt.Line2D([], [], color=c, marker=m, linestyle="", label=f) for f, (c, m) in _STYLE.items()
    ]
    handles.append(
        plt.Line2D(
            [],
            [],
            color="k",
            marker="o",
            markerfacecolor="none",
            linestyle="",
            label="open: float32",
        )
    )
    axes[0][-1].legend(handles=handles, loc="upper right", fontsize=8)
    fig.suptitle("jaxlens: accuracy vs speed (filled: float64, open: float32)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


# ---------------------------------------------------------------------------
# The exact crossings of a sphere at a finite radius


@jax.jit
def _crossing12(alpha, distance, radius):
    c = jaxlens.radius_crossings(alpha, distance, radius, max_windings=MAX_WINDINGS)
    return c.first, c.second, c.count


def run_finite(sets, dtypes, quick):
    """`radius_crossings` at 3 ... 8 duplication steps on the same ray sets, the sphere
    at R = 2D (one crossing) and R = D/2 (two on rays that turn beyond it; the second,
    after the turning point, is compared), against 12 steps in float64 on the same
    (rounded) rays, itself checked against mpmath in tests/test_source_distance.py.

    **Returns:** rows as `row`'s (`status_agree`: the share of rays whose crossing count
    matches the reference's)."""
    rows = []
    steps = (4, 6, 8) if quick else range(3, 9)
    spheres = (("R=2D", 2.0), ("R=D/2", 0.5))

    def pick(c):  # the crossing after the turning point where there are two
        return np.where(np.asarray(c[2]) == 2, np.asarray(c[1]), np.asarray(c[0]))

    def hit(count):
        return np.where(np.asarray(count) > 0, ESCAPED, CAPTURED)

    # The reference once a set, sphere and dtype (its rays rounded to the dtype).
    refs = {
        (name, label, dtype): _crossing12(*(np.asarray(v.astype(dtype), np.float64)
                                            for v in (s["alpha"], s["distance"],
                                                      s["distance"] * factor)))
        for name, s in sets.items() for label, factor in spheres for dtype in dtypes
    }  # fmt: skip
    for n_it in steps:
        for dtype in dtypes:

            @jax.jit
            def f(alpha, distance, radius, n_it=n_it):
                c = jaxlens.radius_crossings(alpha, distance, radius, iterations=n_it,
                                             max_windings=MAX_WINDINGS)  # fmt: skip
                return c.first, c.second, c.count

            for name, s in sets.items():
                for label, factor in spheres:
                    a = s["alpha"].astype(dtype)
                    d = s["distance"].astype(dtype)
                    r = (s["distance"] * factor).astype(dtype)
                    t = time.perf_counter()
                    compiled = f.lower(a, d, r).compile()
                    compile_s = time.perf_counter() - t
                    _, run_s, (first, second, count) = time_call(compiled, a, d, r)
                    ref = refs[name, label, dtype]
                    stats = error_stats(pick((first, second, count)), hit(count), pick(ref),
                                        hit(ref[2]), s["delta"])  # fmt: skip
                    stats["agree"] = float(np.mean(np.asarray(count) == np.asarray(ref[2])))
                    rows.append(row("exact-finite", f"iterations={n_it}", n_it, dtype,
                                    f"{name} {label}", a.size, stats, a.size / run_s,
                                    compile_s))  # fmt: skip
                    print(_progress(rows[-1]), flush=True)
    return rows


def write_finite_markdown(rows, info, path):
    """`results/accuracy_finite.md`: the finite-radius rows as one table."""
    head = [
        "# Accuracy ladder at a finite radius: `radius_crossings` against 12 steps\n",
        "Written by `python benchmarks/accuracy_ladder.py --finite-only` (and by the full",
        "run). The crossing azimuth of the sphere r = R, R = 2D (one crossing) and R = D/2",
        "(the crossing after the turning point is compared), at 3 ... 8 duplication steps",
        "of Carlson's R_F, against 12 steps in float64 on the same rounded rays (checked",
        "against mpmath quadrature to 3e-13 in tests/test_source_distance.py). Ray sets as",
        "in [accuracy_ladder.md](accuracy_ladder.md); `max err (wc)` leaves out the rays",
        "within 1e-5 of the shadow's edge, whose azimuth no method resolves better than",
        "eps / offset; `counts agree`: the share of rays whose crossing count matches.",
        "The errors do not depend on the machine; rays/s do, and move with its load.\n",
        machine_markdown(info),
        f"- Load average (1 min) when written: {load_average():.2f}\n",
    ]
    table = markdown_table(
        ["setting", "dtype", "set", "median err", "max err", "max err (wc)", "counts agree",
         "rays/s", "compile s"],
        [[r["setting"], r["dtype"], r["set"], fmt(r["median_err"]), fmt(r["max_err"]),
          fmt(r["max_err_wc"]), f"{r['status_agree']:.4f}", f"{r['rays_per_s']:.3g}",
          f"{r['compile_s']:.2f}"] for r in rows],
    )  # fmt: skip
    path.write_text("\n".join(head) + "\n" + table)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer rays and settings (~1 min)")
    p.add_argument("--rays", type=int, default=None, help="rays per set for jaxlens methods")
    p.add_argument("--no-float32", action="store_true", help="float64 only")
    p.add_argument(
        "--finite-only", action="store_true",
        help="only the crossings of a sphere at a finite radius (results/accuracy_finite.md)",
    )  # fmt: skip
    p.add_argument(
        "--plot-only", action="store_true", help="redraw pareto.png from the CSV, measure nothing"
    )
    args = p.parse_args(argv)
    if args.plot_only:
        pareto_plot(read_csv(RESULTS / "accuracy_ladder.csv"), RESULTS / "pareto.png")
        return None
    if args.rays is None:
        args.rays = 3_500 if args.quick else 10_500
    args.scipy_rays = 30 if args.quick else 150
    args.diffrax_rays = min(args.rays, 1_000 if args.quick else 3_500)
    args.numpy_rays = args.rays
    n_check = 8 if args.quick else 40
    RESULTS.mkdir(parents=True, exist_ok=True)
    info = machine()
    print(machine_markdown(info), flush=True)

    sets = ray_sets(args.rays)
    dtypes = ("float64",) if args.no_float32 else ("float64", "float32")
    refs = {
        dt: {
            name: reference(s["alpha"].astype(dt), s["distance"].astype(dt))
            for name, s in sets.items()
        }
        for dt in dtypes
    }
    finite = run_finite(sets, dtypes, args.quick)
    write_finite_markdown(finite, info, RESULTS / "accuracy_finite.md")
    if args.finite_only:
        print(f"wrote {RESULTS / 'accuracy_finite.md'}")
        return finite
    check = cross_check(sets, n_check)
    rows = run_jaxlens(sets, refs, dtypes, args.quick)
    table_rows, notes = run_table(sets, refs, dtypes, (1e-6,) if args.quick else (1e-6, 1e-10))
    rows += table_rows
    rows += run_scipy(sets, refs, args.scipy_rays)
    rows += run_diffrax(sets, refs, args.diffrax_rays)
    rows += run_numpy(sets, refs, args.numpy_rays)

    rec = recommendations(rows)
    write_csv(rows, RESULTS / "accuracy_ladder.csv")
    write_markdown(rows, rec, check, info, args, notes, RESULTS / "accuracy_ladder.md")
    pareto_plot(rows, RESULTS / "pareto.png")
    print("RK4 err/dphi^4:", rec["rk4"], "DOPRI err/tol:", rec["dopri5"])
    print("Exact iterations (all rays):", rec["exact_all"], "(wc):", rec["exact_wc"])
    print("fastest:", rec["fastest"])
    print(f"wrote {RESULTS / 'accuracy_ladder.md'}")
    return rows, rec


if __name__ == "__main__":
    main()

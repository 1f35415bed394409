"""The diagnosis pipeline: predict -> locate -> name -> fit and choose -> show.

:func:`diagnose` takes a contract recording and the nominal model that was supposed to
predict it and returns the report (a JSON-able dict, fields documented in
:mod:`.report`); with ``out`` it also writes ``report.json``, ``report.md``, plots and the
improved model (``improved_preset.yaml``).

The candidate fits of each forward-selection step are independent: by default they run on
``Options.n_jobs`` threads of this process (the compiled kernels release the GIL); with
``Options.workers`` or ``Options.cluster`` they are tasks (:func:`_candidate_task`) on an
:class:`experiment_runner.executor.Executor` -- local processes or a Dask cluster. Each
worker process rebuilds the observer from the recording once per diagnosis (cached by a
token), and the fits come back in the order the candidates were submitted, so every path
gives the same report (same effects, bit-identical parameters).
"""
from __future__ import annotations

import contextlib
import math
import os
import pickle
import threading
import time
import uuid
from dataclasses import dataclass, field

import numpy as np

from .data import DiagData, load_data
from .fit import (Evaluator, FitResult, estimate_lattice, fit_effect, fit_noise_level, fit_with, joint_fit, n_eff,
                  noise_components, sparse_regression)
from .hypotheses import LIBRARY, get_effect
from .locate import locate, lowpass
from .model import ModelSpec, load_model
from .predict import (NoiseFloor, Observer, band_rms, compare_replay, open_loop_windows, replay, smoothing_hz,
                      sim_batch, sim_data)

__all__ = ["Options", "diagnose"]

# at most one effect of each group: alternative friction models; and GMS fits the Coulomb force
# itself (the sum of its block capacities)
EXCLUSIVE = ({"dahl", "gms", "stribeck"}, {"gms", "coulomb"})


@dataclass
class Options:
    bandwidth: float | None = None        # force-observer bandwidth [Hz] (default rate/25)
    max_fit_seconds: float = 3.0          # fit set cap (whole trials) [s]
    effects: list | None = None           # restrict the candidates (keys)
    floor_seeds: tuple = (90001, 90002)   # noise seeds of the simulated recordings (floor)
    window_s: float = 0.01                # open-loop window length [s]
    max_steps: int = 3                    # forward-selection steps
    plots: bool = True
    sparse: bool = True
    complexity: float = 0.02              # held-out J penalty per parameter
    n_jobs: int = 2                       # threads for the candidate fits (neither workers nor cluster)
    workers: int | None = None            # candidate fits as tasks on this many local processes (1: in turn here)
    cluster: object = None                # ... on this Dask cluster (scheduler address or cluster object)
    own_floor: bool = True                # judge each candidate against its own noise floor
    min_share: float = 0.25               # after the first effect: share of the remaining excess to explain
    verbose: bool = False
    extra: dict = field(default_factory=dict)


class _Floor:
    """Noise floor of a model on the recorded reference: two simulated recordings."""

    def __init__(self, spec: ModelSpec, data: DiagData, f_o: float, seeds, fs: float):
        self.simA, self.simB = sim_batch(spec, data, seeds[:2])
        oa = Observer(self.simA, bandwidth=f_o, smooth_hz=fs)
        ob = Observer(self.simB, bandwidth=f_o, smooth_hz=fs)
        self.resA = oa.run(spec)
        self.resB = ob.run(spec)
        mA = self.simA.fit | self.simA.held
        self.floor = NoiseFloor(data.rate, [self.resA.r], [mA], f_max=f_o)
        mB = self.simB.held if self.simB.held.any() else self.simB.fit
        self.msB = self.floor.ms(self.resB.r, mB)
        self.n_eff = n_eff(self.floor.whiten(self.resB.r, mB), mB)
        self.band_rms_held = None


def _light_floor(spec: ModelSpec, data: DiagData, f_o: float, seed: int, fs: float) -> NoiseFloor:
    """Noise floor of ``spec`` from one simulated recording."""
    sim = sim_data(spec, data, seed)
    r = Observer(sim, bandwidth=f_o, smooth_hz=fs).run(spec).r
    return NoiseFloor(data.rate, [r], [sim.fit | sim.held], f_max=f_o)


def _fit_candidate(e, current: ModelSpec, selected: list, J_fit_cur: float, ev: Evaluator, ctx: dict,
                   base: ModelSpec, own_floor: bool, floor_seed: int) -> FitResult | None:
    """Fit candidate effect ``e`` on ``current`` (with the ``selected`` effects re-fitted, from
    step 2 on) and judge it on held-out data; None if it does not apply."""
    f = fit_with(e, selected, base, ev, ctx) if selected and e.kind == "deterministic" else None
    f = f or fit_effect(e, current, ev, ctx)
    if f is not None and own_floor:
        # judge the candidate against its own noise floor: a change of the drive or the
        # dynamics also changes what noise leaves in the residual (e.g. a force-constant
        # ratio scales the drive noise). A candidate that does not even fit the fit set
        # better than the current model (against the current floor) may only look good
        # by making its own floor noisier (e.g. a stiff, undamped joint): then the larger
        # of the two counts. One that does fit better is not held back by a quieter own
        # floor (e.g. viscous damping over a quantization-only floor): the smaller counts
        f.J_held_base = f.J_held
        J_own = ev.J(f.spec, "held", floor=_light_floor(f.spec, ev.data, ev.obs.f_o, floor_seed, ev.data.smooth_hz))
        f.J_held = min(J_own, f.J_held_base) if f.J_fit < J_fit_cur else max(J_own, f.J_held_base)
    return f


_STATE: dict = {}                # token -> per-process state of the candidate-fit tasks
_STATE_LOCK = threading.Lock()


def _task_state(token: str, blob: bytes) -> dict:
    """This process's observer and context of diagnosis ``token`` (built from ``blob`` once;
    the last two diagnoses are kept)."""
    with _STATE_LOCK:
        st = _STATE.get(token)
        if st is None:
            st = pickle.loads(blob)
            # the recording was smoothed and masked by the caller's observer: not redone here
            data = st.pop("data")
            st["obs"] = Observer(data, bandwidth=st.pop("f_o"), smooth_hz=data.smooth_hz)
            while len(_STATE) >= 2:
                _STATE.pop(next(iter(_STATE)))
            _STATE[token] = st
        return st


def _candidate_task(token: str, blob: bytes, key: str, current: ModelSpec, selected: list, J_fit_cur: float,
                    floor: NoiseFloor):
    """Executor task: :func:`_fit_candidate` of effect ``key`` against noise ``floor``.

    ``blob`` is the pickled recording (smoothed, masked), observer bandwidth, fit-set cap,
    locate context and base model of diagnosis ``token``. BLAS runs single-threaded, as in
    :func:`diagnose`. Returns ``(FitResult or None, error repr or None, evaluations,
    evaluation seconds)``.
    """
    from threadpoolctl import threadpool_limits
    st = _task_state(token, blob)
    ev = Evaluator(st["obs"], floor, st["max_fit_seconds"])
    e = get_effect(key)
    if hasattr(e, "bind"):
        e.bind(st["ctx"])
    with threadpool_limits(limits=1, user_api="blas"):
        try:
            f, err = _fit_candidate(e, current, selected, J_fit_cur, ev, st["ctx"], st["base"], st["own_floor"],
                                    st["floor_seed"]), None
        except Exception as exc:     # noqa: BLE001 - one bad candidate must not stop the diagnosis
            f, err = None, repr(exc)
    return f, err, ev.evals, ev.seconds


def _log(opt, *a):
    if opt.verbose:
        print("[diagnose]", *a, flush=True)


def _fit_row(f: FitResult, J_cur: float, thr: float, penalty: float) -> dict:
    return {"effect": f.key, "title": f.title, "J_fit": f.J_fit, "J_held": f.J_held,
            "score": f.J_held * (1 + penalty * len(f.theta)), "improvement": J_cur - f.J_held,
            "significant": bool(J_cur - f.J_held > thr), "params": f.params(), "derived": f.derived,
            "on_bound": f.on_bound, "evals": f.evals, "seconds": round(f.seconds, 3)}


def diagnose(recording, nominal, out=None, options: Options | None = None, data: DiagData | None = None) -> dict:
    """Diagnose ``recording`` (path / Recording) against ``nominal`` (preset name/path/model file).

    BLAS runs single-threaded meanwhile (``threadpoolctl``): the diagnosis works on small
    matrices, many at a time on its own threads, where BLAS threads only contend (3x slower
    on a shared 2-core machine).

    Raises
    ------
    stage_sim.config.ConfigError
        ``options.workers`` below 1, or the Dask scheduler ``options.cluster`` cannot be
        reached (before any work is done).
    """
    from threadpoolctl import threadpool_limits
    opt = options or Options()
    with threadpool_limits(limits=1, user_api="blas"), contextlib.ExitStack() as stack:
        ex = None
        if opt.workers is not None or opt.cluster is not None:
            from experiment_runner.executor import make_executor
            ex = stack.enter_context(make_executor(opt.workers, opt.cluster))
            if ex.kind != "inline":
                # start the worker processes (their imports) while this one predicts and locates
                warm = threading.Thread(target=_warm_up, args=(ex,), daemon=True, name="nanostage-diagnose-warm-up")
                warm.start()
                stack.callback(warm.join)          # before the executor closes
        return _diagnose(recording, nominal, out, opt, data, ex)


def _started() -> int:
    """Executor task that does nothing: its worker process has imported this module by now."""
    return os.getpid()


def _warm_up(ex) -> None:
    """Run one :func:`_started` per worker of ``ex`` (a background thread of :func:`diagnose`)."""
    try:
        for _ in ex.map(_started, [(i, ()) for i in range(ex.workers)]):
            pass
    except Exception:    # noqa: BLE001 - a broken pool or a lost scheduler fails the candidate fits themselves
        return


def _fill_plant_inputs(spec: ModelSpec, data, rp: dict) -> list[str]:
    """Give ``data`` the dither forces and SAI command it lacks but the model's plant takes,
    from the nominal closed-loop replay ``rp`` (the model's own dither generator and SAI
    manager on the recorded reference: the switching rule and the dither's open-loop part
    depend on the reference only). Returns the notes for the report."""
    p, notes = spec.preset, []
    if p.dither is not None and data.d0 is None:
        data.d0, data.d1 = rp["d0"], rp["d1"]
        notes.append("dither forces not recorded (/stage/dither): the nominal model's dither generator on the "
                     "recorded reference")
    if p.stage.sai is not None and p.sai_manager is not None and data.mode is None:
        data.mode = rp["mode"]
        notes.append("SAI mode not recorded (/stage/isolator): the nominal model's SAI manager on the recorded "
                     "reference")
    return notes


def _diagnose(recording, nominal, out, opt, data, ex) -> dict:
    T0 = time.perf_counter()
    timing = {}
    t = time.perf_counter()
    data = data if data is not None else load_data(recording)
    timing["read_s"] = time.perf_counter() - t
    spec0 = load_model(nominal)
    notes = list(data.notes)
    rate_p = spec0.preset.controller.rate
    if abs(rate_p - data.rate) > 1e-3 * data.rate:
        notes.append(f"recording rate {data.rate:.6g} Hz differs from the model's controller.rate {rate_p:.6g} Hz; "
                     "the model is run at the recording's rate")
        spec0 = spec0.with_changes({"controller.rate": float(data.rate)})
    t = time.perf_counter()
    rp_nom = replay(spec0, data, seed=opt.floor_seeds[0] + 7)
    notes += _fill_plant_inputs(spec0, data, rp_nom)
    f_o = opt.bandwidth or data.rate / 25.0
    obs = Observer(data, bandwidth=f_o, smooth_hz=smoothing_hz(spec0, data.rate, f_o))
    f_band = obs.f_o / 2
    W = max(8, int(round(opt.window_s * data.rate)))

    # ---------------------------------------------------------------- stochastic: quantization
    found = []           # effects in the order they were named
    stochastic = {}
    base = spec0
    q_nom = spec0.preset.stage.encoder.resolution
    yv = data.y[data.valid]
    q_hat = estimate_lattice(yv)
    q_held = estimate_lattice(data.y[data.held]) if data.held.any() else None
    qinfo = {"nominal_m": q_nom, "estimate_m": q_hat, "held_out_estimate_m": q_held}
    if q_hat is not None and (q_nom == 0 or abs(q_hat / q_nom - 1) > 0.05):
        eff = get_effect("quantization")
        base = eff.apply(base, [q_hat])
        ref = q_held or q_hat
        qinfo.update(found=True, held_out_error_nominal=abs(q_nom - ref) / ref, held_out_error_improved=abs(q_hat - ref) / ref)
        found.append({"effect": "quantization", "title": eff.title, "kind": "stochastic", "step": 0,
                      "params": [{"name": "resolution", "unit": "m", "value": q_hat,
                                  "sigma": abs(q_hat - ref) if q_held else None, "nominal": q_nom}],
                      "derived": {}, "expressible": True, "confounded_with": [],
                      "held_out": {"metric": "relative lattice-step error",
                                   "nominal": qinfo["held_out_error_nominal"], "improved": qinfo["held_out_error_improved"]}})
    else:
        qinfo["found"] = False
        if q_hat is None and q_nom > 0:
            qinfo["note"] = "measured positions are not on a lattice"
    stochastic["quantization"] = qinfo
    _log(opt, "quantization", qinfo)

    # ---------------------------------------------------------------- predict (nominal)
    res_nom = obs.run(spec0, snap_every=W)
    olw_nom = open_loop_windows(spec0, obs, res_nom, W)
    timing["predict_s"] = time.perf_counter() - t
    t = time.perf_counter()
    fl = _Floor(base, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
    timing["floor_s"] = time.perf_counter() - t
    _log(opt, f"floor: sim B ms {fl.msB:.3f}, n_eff {fl.n_eff:.0f}")

    # ---------------------------------------------------------------- locate
    t = time.perf_counter()
    loc, loc_arrays, ctx = locate(data, res_nom, fl.resA, fl.simA, obs.f_o, f_band)
    q_eff = base.preset.stage.encoder.resolution
    ctx["delta_lo"] = max(3 * q_eff, 3e-8)
    ctx["delta_hi"] = max(1e-4, 30 * ctx["delta_lo"])
    timing["locate_s"] = time.perf_counter() - t

    # ---------------------------------------------------------------- fit and choose
    t = time.perf_counter()
    ev = Evaluator(obs, fl.floor, opt.max_fit_seconds)
    Jf0, Jh0, _ = ev.both(spec0)
    Jfb, Jhb, _ = ev.both(base) if base is not spec0 else (Jf0, Jh0, 0)
    neff = max(fl.n_eff, 10.0)
    tol_ad = max(0.1, 3 * math.sqrt(2 / neff), 2 * abs(fl.msB - 1))

    def thr(J):
        return max(6 * math.sqrt(max(J, 1.0) / neff), 0.05 * max(J - 1, 0.0), 0.02)

    keys = opt.effects or [k for k, e in LIBRARY.items() if e.kind in ("deterministic", "integer")]

    def candidates(current, selected):
        taken = {f.key for f in selected}
        excl = set().union(*[g for g in EXCLUSIVE if g & taken]) if taken else set()
        todo = []
        for k in keys:
            e = get_effect(k)
            if k in taken or k in excl or e.kind not in ("deterministic", "integer") or e.applicable(current) is not None:
                continue
            if hasattr(e, "bind"):
                e.bind(ctx)
            todo.append(e)
        return todo

    def fit_all(todo, current, selected, J_fit_cur):
        """Fit every candidate (with the selected effects re-fitted, from step 2 on)."""
        # slow (multi-parameter, stiff) candidates first for a better balance; the fits are
        # collected in this order on every path (ties of the score below keep it)
        todo.sort(key=lambda e: -len(e.params(current, ctx)))
        if ex is not None:
            args = (current, selected, J_fit_cur, ev.floor)
            out = [None] * len(todo)
            for i, (f, err, n, sec) in ex.map(_candidate_task, ((i, (token, blob, e.key) + args)
                                                                 for i, e in enumerate(todo))):
                ev.evals += n
                ev.seconds += sec
                if err is not None:
                    _log(opt, f"fit {todo[i].key} failed: {err}")
                out[i] = f
            fits = [f for f in out if f is not None]
        else:
            def _one(e):
                try:
                    return _fit_candidate(e, current, selected, J_fit_cur, ev, ctx, base, opt.own_floor,
                                          opt.floor_seeds[0])
                except Exception as err:     # noqa: BLE001 - one bad candidate must not stop the diagnosis
                    _log(opt, f"fit {e.key} failed: {err!r}")
                    return None
            # the compiled kernels release the GIL: candidates are fitted on parallel threads
            current.compiled()
            if opt.n_jobs > 1 and len(todo) > 1:
                from concurrent.futures import ThreadPoolExecutor
                with ThreadPoolExecutor(opt.n_jobs) as pool:
                    fits = [f for f in pool.map(_one, todo) if f is not None]
            else:
                fits = [f for f in map(_one, todo) if f is not None]
        fits.sort(key=lambda f: f.J_held * (1 + opt.complexity * len(f.theta)))
        return fits

    def forward():
        """Forward selection from ``base``: each step fits every candidate (re-fitting the
        selected ones with it) and keeps the best if it is a real improvement."""
        path = {"current": base, "J_cur": Jhb, "J_fit": Jfb, "floor": fl, "steps": [], "selected": [], "found": []}
        selected = path["selected"]

        def adopt(jf):
            """Keep the re-fitted values of the selected deterministic effects (joint fit ``jf``)."""
            k = 0
            for f, fe in zip(selected, path["found"]):
                if LIBRARY[f.key].kind != "deterministic":
                    continue
                n = len(f.theta)
                f.theta, f.sigma = jf.theta[k:k + n], jf.sigma[k:k + n]
                fe["params"] = f.params()
                fe["derived"] = LIBRARY[f.key].derived(base, f.theta)
                k += n

        for step in range(1, opt.max_steps + 1):
            for _ in range(3 if step > 1 else 0):
                # continue the fit of the selected effects alone first: a candidate is credited only
                # with what it adds to them (not with what more iterations on them would give)
                rf = joint_fit(selected, base, ev, ctx, min_effects=1, max_iter=8)
                if rf is None or not rf.J_held < path["J_cur"] - thr(path["J_cur"]):
                    break
                adopt(rf)
                path.update(current=rf.spec, J_cur=rf.J_held, J_fit=rf.J_fit)
            if step > 1 and path["J_cur"] <= 1 + tol_ad:
                break
            current, J_cur = path["current"], path["J_cur"]
            fits = fit_all(candidates(current, selected), current, selected, path["J_fit"])
            if not fits:
                break
            th = thr(J_cur)
            # statistically equivalent candidates (held-out J within run-to-run noise of the best):
            # name the simplest of them first (fewest parameters, then score), report the others
            th_b = thr(fits[0].J_held)
            equiv = [f for f in fits if f.J_held - fits[0].J_held < th_b]
            best = min(equiv, key=lambda f: (len(f.theta), f.J_held * (1 + opt.complexity * len(f.theta))))
            fits.remove(best)
            fits.insert(0, best)
            rows = [_fit_row(f, J_cur, th, opt.complexity) for f in fits]
            # a real improvement: beyond run-to-run noise, and after the first effect a real share of
            # what remains (so the remnant of an imperfect structural fit is not "explained" by extras)
            share = (J_cur - best.J_held) / max(J_cur - 1.0, 1e-300)
            accept = (J_cur > 1 + tol_ad) and (J_cur - best.J_held > th) and (step == 1 or share >= opt.min_share)
            conf = []
            if accept:
                conf = [f.key for f in equiv if f is not best and (J_cur - f.J_held) > th]
            path["steps"].append({"step": step, "J_held_before": J_cur, "threshold": th,
                                  "adequate_before": J_cur <= 1 + tol_ad, "accepted": best.key if accept else None,
                                  "confounded_with": conf, "share_of_excess": share, "candidates": rows})
            _log(opt, f"step {step}: J {J_cur:.4g} -> best {best.key} {best.J_held:.4g} (thr {th:.3g}) accept={accept}")
            if not accept:
                break
            if best.joint is not None:
                adopt(best.joint)           # the selected effects were re-fitted with this one
            refit = None
            if best.joint is None and step > 1:
                # an integer effect (delay) was fitted with the others held: re-fit them now
                refit = joint_fit(selected + [best], base, ev, ctx, min_effects=1)
                if refit is not None:
                    adopt(refit)
            selected.append(best)
            alts = [{"effect": r["effect"], "title": r["title"], "params": r["params"], "derived": r["derived"],
                     "J_held": r["J_held"]} for r in rows if r["effect"] in conf]
            path["found"].append({"effect": best.key, "title": best.title, "kind": "deterministic", "step": step,
                                  "params": best.params(), "derived": best.derived, "expressible": best.expressible,
                                  "confounded_with": conf, "alternatives": alts, "J_held": best.J_held})
            path["current"] = refit.spec if refit is not None else best.spec
            path["floor"] = _Floor(path["current"], data, obs.f_o, opt.floor_seeds, data.smooth_hz)
            ev.floor = path["floor"].floor
            path["J_fit"], path["J_cur"], _ = ev.both(path["current"])
            if path["J_cur"] <= 1 + tol_ad:
                break
        return path

    # candidate fits as executor tasks (local processes / Dask): what every task needs, once
    token, blob = None, None
    if ex is not None:
        token = uuid.uuid4().hex
        blob = pickle.dumps({"data": data, "f_o": obs.f_o, "max_fit_seconds": opt.max_fit_seconds, "ctx": ctx,
                             "base": base, "own_floor": opt.own_floor, "floor_seed": opt.floor_seeds[0]},
                            protocol=pickle.HIGHEST_PROTOCOL)
    path = forward()
    with _STATE_LOCK:
        _STATE.pop(token, None)     # this process's copy (executor running the tasks here, workers=1)
    current, J_cur, floor_cur = path["current"], path["J_cur"], path["floor"]
    steps, selected = path["steps"], path["selected"]
    found += path["found"]

    # joint fit of the selected deterministic effects
    joint = None
    if len([f for f in selected if LIBRARY[f.key].kind == "deterministic"]) >= 2:
        try:
            jf = joint_fit(selected, base, ev, ctx)
        except Exception as err:   # noqa: BLE001
            jf = None
            _log(opt, f"joint fit failed: {err!r}")
        if jf is not None:
            joint = {"effects": jf.key, "J_fit": jf.J_fit, "J_held": jf.J_held, "params": jf.params(),
                     "correlation": jf.corr.tolist() if jf.corr is not None else None,
                     "used": bool(jf.J_held <= J_cur + 0.5 * thr(J_cur))}
            conf_pairs = []
            if jf.corr is not None:
                for i in range(len(jf.names)):
                    for j in range(i + 1, len(jf.names)):
                        if jf.names[i].split(".")[0] != jf.names[j].split(".")[0] and abs(jf.corr[i, j]) > 0.95:
                            conf_pairs.append([jf.names[i], jf.names[j], float(jf.corr[i, j])])
            joint["confounded_parameters"] = conf_pairs
            if joint["used"]:
                current = jf.spec
                # report the jointly fitted values on the found effects
                for fe in found:
                    if fe["kind"] != "deterministic":
                        continue
                    fe["params_joint"] = [p for p in jf.params() if p["name"].split(".")[0] == fe["effect"]]
                J_cur = ev.J(current, "held")
    timing["fit_s"] = time.perf_counter() - t

    # ---------------------------------------------------------------- stochastic: drive noise
    t = time.perf_counter()
    ninfo = {"nominal_A": spec0.preset.stage.drive.noise_current_rms, "found": False}
    try:
        comps = noise_components(current, data, lambda d: Observer(d, bandwidth=obs.f_o, smooth_hz=data.smooth_hz), seeds=tuple(opt.floor_seeds[0] + 11 + i for i in range(4)))
        r_cur = obs.run(current).r
        est = fit_noise_level(r_cur, data.fit, data.rate, comps, f_max=0.75 * obs.f_o)
        ninfo.update({k: v for k, v in est.items() if k != "ok"})
        s0 = current.preset.stage.drive.noise_current_rms
        if est.get("ok"):
            sig = est["sigma"]
            ratio = sig / s0 if s0 > 0 else float("inf")
            ninfo["ratio"] = ratio if s0 > 0 else None
            consistent = est.get("spread", 1.0) < 0.35
            ninfo["consistent"] = consistent
            if not (0.8 <= ratio <= 1.25) and consistent:
                cand = get_effect("noise_level").apply(current, [sig])
                fl2 = _Floor(cand, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
                J_old = J_cur
                J_new = fl2.floor.ms(r_cur, data.held) if data.held.any() else fl2.floor.ms(r_cur, data.fit)
                ninfo.update({"J_held_before": J_old, "J_held_after": J_new})
                if abs(J_new - 1) + 0.5 * tol_ad < abs(J_old - 1):
                    ninfo["found"] = True
                    found.append({"effect": "noise_level", "title": LIBRARY["noise_level"].title, "kind": "stochastic",
                                  "step": len(steps) + 1,
                                  "params": [{"name": "noise_current_rms", "unit": "A", "value": sig,
                                              "sigma": est.get("sigma_unc"), "nominal": s0}],
                                  "derived": {}, "expressible": True, "confounded_with": [],
                                  "held_out": {"metric": "|J_held - 1| (floor mismatch)", "nominal": abs(J_old - 1),
                                               "improved": abs(J_new - 1)}})
                    current = cand
                    floor_cur = fl2
                    ev.floor = fl2.floor
                    J_cur = J_new
    except Exception as err:   # noqa: BLE001
        ninfo["error"] = repr(err)
    stochastic["noise_level"] = ninfo
    timing["noise_s"] = time.perf_counter() - t

    # ---------------------------------------------------------------- validation on held-out data
    t = time.perf_counter()
    held = data.held if data.held.any() else data.fit
    res_new = obs.run(current, snap_every=W)
    r_nom_band = band_rms(res_nom.r, held, data.rate, f_band)
    r_new_band = band_rms(res_new.r, held, data.rate, f_band)
    floor_band = band_rms(floor_cur.resB.r, floor_cur.simB.held if floor_cur.simB.held.any() else floor_cur.simB.fit,
                          data.rate, f_band)
    J_nom_held = fl.floor.ms(res_nom.r, held)         # each model against its own floor
    J_new_held = ev.floor.ms(res_new.r, held)
    hcols = [b for b in range(data.shape[1]) if held[:, b].any()]
    rp_new = replay(current, data, seed=opt.floor_seeds[0] + 7)
    hm = np.zeros_like(held)
    hm[:, hcols] = data.valid[:, hcols]
    # run-to-run: two simulated recordings of the improved model
    rr = {"u": floor_cur.simA.u, "y": floor_cur.simA.y}
    def _rp(rp):
        du = (data.u - rp["u"])[hm]
        dy = (data.y - rp["y"])[hm]
        return float(np.sqrt(np.mean(du ** 2))), float(np.sqrt(np.mean(dy ** 2)))
    cu_nom, cy_nom = _rp(rp_nom)
    cu_new, cy_new = _rp(rp_new)
    cu_rr = float(np.sqrt(np.mean((floor_cur.simB.u - rr["u"])[hm] ** 2)))
    cy_rr = float(np.sqrt(np.mean((floor_cur.simB.y - rr["y"])[hm] ** 2)))
    olw_new = open_loop_windows(current, obs, res_new, W)

    def _olw_rms(o):
        if o is None:
            return None
        sel = np.array([held[o["start"][i], o["trial"][i]] for i in range(len(o["start"]))])
        return float(np.sqrt(np.mean(o["drift_m"][sel] ** 2))) if sel.any() else None

    def _fall(a, b):
        return float(1 - b / a) if a and a > 0 else None

    validation = {
        "held_out_samples": int(held.sum()),
        "force_residual_rms_N": {"nominal": r_nom_band, "improved": r_new_band, "floor": floor_band,
                                 "fall": _fall(r_nom_band, r_new_band)},
        "J_held": {"nominal": J_nom_held, "improved": J_new_held, "fall": _fall(J_nom_held, J_new_held)},
        "replay_command_rms_N": {"nominal": cu_nom, "improved": cu_new, "run_to_run": cu_rr,
                                 "fall": _fall(cu_nom, cu_new)},
        "replay_position_rms_m": {"nominal": cy_nom, "improved": cy_new, "run_to_run": cy_rr,
                                  "fall": _fall(cy_nom, cy_new)},
        "open_loop_drift_rms_m": {"nominal": _olw_rms(olw_nom), "improved": _olw_rms(olw_new),
                                  "window_s": W / data.rate},
    }
    timing["validate_s"] = time.perf_counter() - t

    # ---------------------------------------------------------------- sparse regression (unexplained)
    adequate_final = J_cur <= 1 + tol_ad
    sparse = None
    if opt.sparse and not adequate_final:
        t = time.perf_counter()
        sparse = _sparse(data, res_new, ctx, f_band)
        timing["sparse_s"] = time.perf_counter() - t

    if not found:
        verdict = "model adequate" if (Jh0 <= 1 + tol_ad) else "unexplained residual"
    else:
        verdict = "effects found" if adequate_final else "effects found, residual remains"
    timing["total_s"] = time.perf_counter() - T0
    report = {
        "nanostage_diagnosis": 1,
        "verdict": verdict,
        "found": found,
        "recording": {"source": data.source, "rate_hz": data.rate, "trials": int(data.shape[1]),
                      "samples": int(data.valid.sum()), "duration_s": float(data.valid.sum() / data.rate),
                      "split": data.split, "fit_trials": [int(data.trial_ids[c]) for c in ev.fit_cols],
                      "held_out_trials": [int(data.trial_ids[c]) for c in ev.held_cols], "notes": notes},
        "nominal": {"name": spec0.preset.name, "source": str(nominal) if not isinstance(nominal, (dict,)) else "<mapping>"},
        "observer": {"bandwidth_hz": obs.f_o, "smoothing_hz": data.smooth_hz, "band_hz": f_band,
                     "evaluations": ev.evals, "evaluation_s": ev.seconds},
        "noise": {"floor_check_J": fl.msB, "n_eff_held": neff, "adequacy_tolerance": tol_ad},
        "predict": {
            "closed_loop_replay": compare_replay(data, rp_nom),
            "force_residual": {"rms_N": band_rms(res_nom.r, data.fit | data.held, data.rate, f_band),
                               "floor_rms_N": loc["floor_rms_N"], "J_fit": Jf0, "J_held": Jh0,
                               "observer_failures": res_nom.bad},
            "open_loop_windows": None if olw_nom is None else {
                "window_s": W / data.rate, "windows": int(len(olw_nom["start"])),
                "rms_drift_m": float(np.sqrt(np.mean(olw_nom["drift_m"] ** 2))),
                "rms_force_N": float(np.sqrt(np.mean(olw_nom["force_N"] ** 2)))},
        },
        "locate": loc,
        "selection": {"steps": steps, "J_held_start": Jhb, "J_held_final": J_cur, "adequate_final": adequate_final},
        "joint_fit": joint,
        "stochastic": stochastic,
        "sparse_regression": sparse,
        "validation": validation,
        "improved_model": {"name": current.preset.name},
        "timing_s": timing,
    }
    if out is not None:
        from .report import write_report
        write_report(out, report, current, spec0, data,
                     {"res_nom": res_nom, "res_new": res_new, "loc": loc_arrays, "rp_nom": rp_nom, "rp_new": rp_new,
                      "held": held, "f_band": f_band, "floor": floor_cur}, plots=opt.plots)
        report["timing_s"]["total_s"] = time.perf_counter() - T0
    report["_improved_spec"] = current
    return report


def _sparse(data, res, ctx, f_band):
    """SINDy-style regression of the remaining (band-limited) residual on state functions."""
    mask = data.fit | data.held
    rl = lowpass(res.r, mask, data.rate, f_band)
    x, v = res.x, data.vs
    acc = lowpass(np.gradient(data.vs, axis=0) * data.rate, data.valid, data.rate, f_band)
    xc, xs = ctx.get("x_center", 0.0), max(ctx.get("x_half_span", 1e-3), 1e-12)
    vmax = max(ctx.get("v_max", 1e-3), 1e-12)
    xi = (x - xc) / xs
    feats = {"1": np.ones_like(x), "v": v, "sign(v)": np.tanh(v / (0.01 * vmax)), "v|v|": v * np.abs(v),
             "|v|": np.abs(v), "|phi_f|": np.abs(res.phi),
             "x": xi, "x^2": xi ** 2, "a": acc, "u": data.u, "phi_f": res.phi, "phi_f*x": res.phi * xi,
             "phi_f*x^2": res.phi * xi ** 2}
    per = (ctx.get("ripple_period") or [None])[0]
    if per:
        feats[f"sin(2pi x/{per:.3g})"] = np.sin(2 * np.pi * x / per)
        feats[f"cos(2pi x/{per:.3g})"] = np.cos(2 * np.pi * x / per)
    target = rl[mask]
    out = sparse_regression({k: lowpass(f_, mask, data.rate, f_band)[mask] for k, f_ in feats.items()}, target)
    out["units"] = "missing table force [N] = sum coef * term; x normalised: (x - x_center)/x_half_span"
    out["x_center_m"], out["x_half_span_m"] = xc, xs
    return out

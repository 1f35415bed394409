"""Friction identification on the reciprocating micro-tribometer record (``shared/data/microtribometer_reciprocating``).

Why not the diagnosis pipeline
------------------------------
The record is friction force against the position of the driven side of a contact under a
5 N normal load. There is no controller, no command and no moving mass to identify: the
position is imposed, and the friction force is *measured*. So there is nothing to replay in
closed loop and no force residual to observe; the honest use of the project's friction
models is the open-loop, position-driven identification they were built for
(:mod:`stage_sim.friction`): each model is driven by the measured displacement history and
its force is compared with the measured one. The same models as the diagnosis' hypothesis
library are candidates (plain Coulomb, Dahl, generalized Maxwell-slip, LuGre/Stribeck), each
with a constant force offset (the sensor's zero is not documented). They are fitted on two of
every three strokes between reversals and judged on the third (held out), as the diagnosis
splits its records.

Conventions
-----------
Friction ``F`` [N] is the force that *resists* the motion (:mod:`stage_sim.friction`): the
recorded column is ``-F`` (the source flips its sign, README), i.e. ``F = -Friction[uN]*1e-6``.
Only samples with the normal load held (>= 98 % of its maximum) are used; the models start
relaxed (virgin contact) at the first of them, and the stroke before the first reversal is in
neither set. The position is
quantized at 0.1 um; the rate-independent models (Dahl, GMS) need only its increments. With a
single sliding speed (~0.114 mm/s), a viscous term is not separable from the Coulomb level and
is left out; LuGre's bristle damping ``sigma1`` (5 ms samples of a 0.1-um-quantized position)
is not identifiable either and is fixed at 0.

Transition length
-----------------
``x_zero``: displacement after a reversal at which the force changes sign; ``x_80``: at which
it reaches 80 % of the new sliding level (README: ~0.06 mm and ~0.10 mm). Measured on every
stroke of the record and computed for each fitted model on the same strokes.

:func:`run_tribometer` is the data set's run of ``nanostage realdata``: the record read and
identified, its checksum, the README's values beside the results, and the plot.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
from numba import njit
from scipy.optimize import least_squares, nnls

from experiment_runner.core import outputs
from experiment_runner.core.tabular import sha256
from stage_sim.friction import dahl_update, gms_update, lugre_update

from .datasets import DataMissing, need_file

__all__ = ["TribData", "load_tribometer", "identify_tribometer", "transition_lengths", "run_tribometer"]

GMS_BLOCKS = 10
GMS_DELTA = (2e-6, 3e-4)       # slip displacements of the GMS blocks, log-spaced [m]
# LuGre: Stribeck peak F_S <= 3 F_C. Unbounded, the fit takes F_S ~ 60 F_C so that the bristle
# state never reaches steady sliding within a 0.23 mm stroke (a degenerate, unphysical fit).
LUGRE_MAX_RATIO = 3.0


@dataclass
class TribData:
    """Used part of the record (SI): time [s], position [m], friction [N], normal force [N].

    Parameters
    ----------
    t : numpy.ndarray
        Time [s].
    x : numpy.ndarray
        Position [m].
    f : numpy.ndarray
        Friction force [N].
    normal : numpy.ndarray
        Normal force [N].
    rev : numpy.ndarray
        Sample index of each reversal (start of a stroke).
    path : pathlib.Path
        The file read.
    """
    t: np.ndarray
    x: np.ndarray
    f: np.ndarray
    normal: np.ndarray
    rev: np.ndarray          # sample index of each reversal (start of a stroke)
    path: Path

    @property
    def strokes(self) -> list[tuple[int, int]]:
        """``(start, stop)`` sample ranges between consecutive reversals."""
        return [(int(a), int(b)) for a, b in zip(self.rev[:-1], self.rev[1:])]


def _reversals(x: np.ndarray, threshold: float) -> np.ndarray:
    """Index of the last sample at each turning point of ``x`` (hysteresis ``threshold`` [m])."""
    out = []
    direction = 0
    hi, hi_i, lo, lo_i = x[0], 0, x[0], 0
    for i in range(1, len(x)):
        if x[i] >= hi:
            hi, hi_i = x[i], i
        if x[i] <= lo:
            lo, lo_i = x[i], i
        if direction >= 0 and hi - x[i] > threshold:
            if direction > 0:
                out.append(hi_i)
            direction, lo, lo_i = -1, x[i], i
        elif direction <= 0 and x[i] - lo > threshold:
            if direction < 0:
                out.append(lo_i)
            direction, hi, hi_i = 1, x[i], i
    return np.array(out, int)


def load_tribometer(path) -> TribData:
    """Read ``test_data_2.txt`` (tab-separated, one header line) into SI; find the reversals.

    Parameters
    ----------
    path : str or pathlib.Path
        The file.

    Returns
    -------
    TribData
    """
    path = Path(path)
    if not path.is_file():
        raise DataMissing(f"tribometer data: {path} does not exist")
    try:
        a = np.loadtxt(path, skiprows=1)
    except ValueError as err:
        raise ValueError(f"{path}: not a 4-column numeric table after the header ({err})") from None
    if a.ndim != 2 or a.shape[1] != 4 or len(a) < 100:
        raise ValueError(f"{path}: expected >= 100 rows of 4 columns (time, normal, position, friction), "
                         f"got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{path}: non-finite values")
    t, n, x, f = a.T
    if not np.all(np.diff(t) > 0):
        raise ValueError(f"{path}: time must increase strictly")
    keep = n >= 0.98 * n.max()
    i0 = int(np.argmax(keep))
    sl = slice(i0, len(t))
    x_m = x[sl] * 1e-3
    rev = _reversals(x_m, threshold=5e-6)
    if len(rev) < 6:
        raise ValueError(f"{path}: only {len(rev)} reversals found under load")
    return TribData(t=t[sl], x=x_m, f=-f[sl] * 1e-6, normal=n[sl] * 1e-6, rev=rev, path=path)


# --------------------------------------------------------------------------- model kernels
@njit(cache=True)
def _coulomb_sign(x):
    """Sign of the last nonzero displacement increment (0 before the first)."""
    out = np.zeros(x.shape[0])
    s = 0.0
    for i in range(1, x.shape[0]):
        dx = x[i] - x[i - 1]
        if dx > 0.0:
            s = 1.0
        elif dx < 0.0:
            s = -1.0
        out[i] = s
    return out


@njit(cache=True)
def _dahl(x, k, fc, shape, f0):
    out = np.empty(x.shape[0])
    f = f0
    out[0] = f
    for i in range(1, x.shape[0]):
        f = dahl_update(f, x[i] - x[i - 1], k, fc, shape)
        out[i] = f
    return out


@njit(cache=True)
def _gms_basis(x, delta, f0):
    """Unit-capacity elasto-slip blocks (slip at 1 N after ``delta_i``): (T, n) forces."""
    n = delta.shape[0]
    out = np.empty((x.shape[0], n))
    k = 1.0 / delta
    alpha = np.ones(n)
    st = np.full(n, f0)
    for j in range(n):
        out[0, j] = st[j]
    for i in range(1, x.shape[0]):
        gms_update(st, x[i] - x[i - 1], k, alpha, 1.0, n)
        for j in range(n):
            out[i, j] = st[j]
    return out


@njit(cache=True)
def _lugre(x, t, sigma0, fc, fs, vs, z0):
    out = np.empty(x.shape[0])
    z = z0
    out[0] = sigma0 * z
    for i in range(1, x.shape[0]):
        z, f = lugre_update(z, x[i] - x[i - 1], t[i] - t[i - 1], sigma0, 0.0, fc, fs, vs, 2.0)
        out[i] = sigma0 * z
    return out


# --------------------------------------------------------------------------- identification
class _Candidate(NamedTuple):
    """A friction model to fit: parameter names and units, force prediction ``predict(theta)``
    [N] over the whole record; linear models give their regressors ``cols`` (capacities >= 0,
    then a free offset), nonlinear ones a start ``x0`` and box ``bounds`` (fitted in log for
    the ``log`` parameters)."""
    names: list
    units: list
    predict: Callable
    cols: np.ndarray | None = None
    x0: list | None = None
    bounds: tuple | None = None
    log: tuple = ()


def _candidates(d: TribData) -> dict[str, _Candidate]:
    """The candidate models on this record (all start relaxed at the first used sample)."""
    x, t = d.x, d.t
    sgn = _coulomb_sign(x)
    fc0 = float(np.median(np.abs(d.f)))
    delta = np.logspace(np.log10(GMS_DELTA[0]), np.log10(GMS_DELTA[1]), GMS_BLOCKS)
    basis = _gms_basis(x, delta, 0.0)
    return {
        "coulomb": _Candidate(["F_C", "offset"], ["N", "N"], lambda th: th[0] * sgn + th[1], cols=sgn[:, None]),
        "dahl": _Candidate(["k_sigma", "F_C", "shape", "offset"], ["N/m", "N", "-", "N"],
                           lambda th: _dahl(x, th[0], th[1], th[2], 0.0) + th[3],
                           x0=[fc0 / 3e-5, fc0, 1.0, 0.0],
                           bounds=([fc0 / 1e-2, 0.1 * fc0, 0.02, -fc0], [fc0 / 1e-7, 3 * fc0, 5.0, fc0]),
                           log=("k_sigma", "shape")),
        "lugre": _Candidate(["sigma0", "F_C", "F_S/F_C", "v_s", "offset"], ["N/m", "N", "-", "m/s", "N"],
                            lambda th: _lugre(x, t, th[0], th[1], th[1] * th[2], th[3], 0.0) + th[4],
                            x0=[fc0 / 3e-5, fc0, 1.2, 5e-5, 0.0],
                            bounds=([fc0 / 1e-2, 0.1 * fc0, 1.0001, 1e-7, -fc0],
                                    [fc0 / 1e-7, 3 * fc0, LUGRE_MAX_RATIO, 1e-2, fc0]),
                            log=("sigma0", "F_S/F_C", "v_s")),
        "gms": _Candidate([f"F_{i + 1}" for i in range(GMS_BLOCKS)] + ["offset"], ["N"] * (GMS_BLOCKS + 1),
                          lambda th: basis @ np.asarray(th[:GMS_BLOCKS]) + th[GMS_BLOCKS], cols=basis),
    }


def _fit_linear(cols: np.ndarray, f: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of ``f`` on ``cols`` (coefficients >= 0) plus a free offset, on ``mask``.

    Returns the coefficients (offset last) and the Jacobian of the prediction on ``mask``.
    """
    n, k = cols.shape
    A = np.column_stack([cols, np.ones(n), -np.ones(n)])[mask]
    th, _ = nnls(A, f[mask])
    return np.r_[th[:k], th[k] - th[k + 1]], A[:, :k + 1]


def _fit_nonlinear(c: _Candidate, f: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounded least squares (three starts of the first parameter), log-scaled where asked."""
    logp = np.array([n in c.log for n in c.names])
    lo, hi = (np.asarray(b, float) for b in c.bounds)

    def to_z(th):
        return np.where(logp, np.log(np.where(logp, np.abs(th), 1.0)), th)

    def res(z):
        return (c.predict(np.where(logp, np.exp(z), z)) - f)[mask]
    best = None
    for scale in (1.0, 0.3, 3.0):
        th0 = np.array(c.x0, float)
        th0[0] *= scale
        r = least_squares(res, to_z(np.clip(th0, lo, hi)), bounds=(to_z(lo), to_z(hi)), x_scale="jac", max_nfev=200)
        if best is None or r.cost < best.cost:
            best = r
    th = np.where(logp, np.exp(best.x), best.x)
    return th, best.jac / np.where(logp, th, 1.0)[None, :]


def _sigma(jac: np.ndarray, res: np.ndarray) -> np.ndarray:
    """Standard errors from the Jacobian of the residual (white-noise approximation)."""
    n, p = jac.shape
    s2 = float(res @ res) / max(n - p, 1)
    try:
        cov = np.linalg.pinv(jac.T @ jac) * s2
        return np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        return np.full(p, np.nan)


def transition_lengths(d: TribData, f: np.ndarray, strokes=None) -> dict:
    """Median ``x_zero`` and ``x_80`` [m] over strokes (see module docstring) of force ``f``.

    Parameters
    ----------
    d : TribData
        The record.
    f : numpy.ndarray
        Friction force [N] per sample (measured or predicted).
    strokes : list of tuple, optional
        ``(start, stop)`` ranges (default all).

    Returns
    -------
    dict
        ``x_zero_m`` and ``x_80_m`` (NaN without a stroke), ``strokes``.
    """
    xz, x8 = [], []
    for a, b in (strokes or d.strokes):
        s = np.sign(d.x[b - 1] - d.x[a])
        disp = s * (d.x[a:b] - d.x[a])
        fs = s * f[a:b]
        slide = (disp > 0.15e-3) & (disp < 0.2e-3)
        if s == 0 or not slide.any() or disp.max() < 0.2e-3:
            continue
        level = float(np.median(fs[slide]))
        iz = np.flatnonzero(fs > 0)
        i8 = np.flatnonzero(fs >= 0.8 * level)
        if len(iz) and len(i8):
            xz.append(disp[iz[0]])
            x8.append(disp[i8[0]])
    return {"x_zero_m": float(np.median(xz)) if xz else float("nan"),
            "x_80_m": float(np.median(x8)) if x8 else float("nan"), "strokes": len(xz)}


def identify_tribometer(d: TribData, held_every: int = 3) -> dict:
    """Fit every candidate model on the fit strokes, judge on the held-out strokes.

    Returns a JSON-able dict: per model its parameters (value, sigma, unit), RMS error [N]
    on fit and held-out strokes (all samples, and the transition part: displacement since
    the reversal < 0.15 mm), transition lengths; the winner (lowest held-out RMS), the
    measured transition lengths, and the split. Sigmas are the white-noise least-squares
    approximation: the residuals are correlated along a stroke, so they are lower bounds.

    Parameters
    ----------
    d : TribData
        The record.
    held_every : int, optional
        Every this many strokes is held out.

    Returns
    -------
    dict
    """
    strokes = d.strokes
    held_ix = [j for j in range(len(strokes)) if j % held_every == held_every - 1]
    fit_m = np.zeros(len(d.x), bool)
    held_m = np.zeros(len(d.x), bool)
    trans_m = np.zeros(len(d.x), bool)
    for j, (a, b) in enumerate(strokes):
        (held_m if j in held_ix else fit_m)[a:b] = True
        s = np.sign(d.x[b - 1] - d.x[a])
        trans_m[a:b] = s * (d.x[a:b] - d.x[a]) < 0.15e-3
    cands = _candidates(d)
    f = d.f
    out = {}
    for name, c in cands.items():
        th, jac = (_fit_linear(c.cols, f, fit_m) if c.cols is not None else _fit_nonlinear(c, f, fit_m))
        fp = c.predict(th)
        sig = _sigma(jac, (fp - f)[fit_m])
        rms = lambda m: float(np.sqrt(np.mean((fp - f)[m] ** 2)))  # noqa: E731
        out[name] = {"params": [{"name": n, "unit": u, "value": float(v), "sigma": float(s)}
                                for n, u, v, s in zip(c.names, c.units, th, sig)],
                     "rms_fit_N": rms(fit_m), "rms_held_N": rms(held_m),
                     "rms_held_transition_N": rms(held_m & trans_m), "n_params": len(th),
                     "transition_held": transition_lengths(d, fp, [strokes[j] for j in held_ix]), "_pred": fp}
    out["gms"]["slip_displacements_m"] = list(np.logspace(np.log10(GMS_DELTA[0]), np.log10(GMS_DELTA[1]), GMS_BLOCKS))
    out["gms"]["derived"] = {"F_C": float(sum(p["value"] for p in out["gms"]["params"][:GMS_BLOCKS]))}
    win = min(out, key=lambda k: out[k]["rms_held_N"])
    fc_win = {"coulomb": lambda e: e["params"][0]["value"], "dahl": lambda e: e["params"][1]["value"],
              "lugre": lambda e: e["params"][1]["value"], "gms": lambda e: e["derived"]["F_C"]}
    out["lugre"]["derived"] = {"F_S": out["lugre"]["params"][1]["value"] * out["lugre"]["params"][2]["value"]}
    normal = float(np.median(d.normal))
    for k, e in out.items():
        e["mu_C"] = fc_win[k](e) / normal
    return {
        "source": str(d.path), "samples": int(len(d.x)), "duration_s": float(d.t[-1] - d.t[0]),
        "normal_force_N": normal, "reversals": int(len(d.rev)), "strokes": len(strokes),
        "held_out_strokes": held_ix,
        "split": f"stroke j held out if j % {held_every} == {held_every - 1} ({len(held_ix)} of {len(strokes)})",
        "measured_transition": transition_lengths(d, f),
        "measured_transition_held": transition_lengths(d, f, [strokes[j] for j in held_ix]),
        "sliding_level_N": float(np.median(np.abs(f[~trans_m & (fit_m | held_m)]))),
        # the README's statistic: median |F/N| over the moving samples (|v| > 20 um/s)
        "mu_moving_median": float(np.median(np.abs(f / d.normal)[np.abs(np.gradient(d.x, d.t)) > 2e-5])),
        "models": out, "winner": win,
        "_masks": {"fit": fit_m, "held": held_m, "transition": trans_m},
    }


def run_tribometer(root: Path, out: Path, plots: bool = True) -> dict:
    """The tribometer's section of the realdata report: the open-loop, position-driven friction
    identification (:func:`identify_tribometer`) of the record under ``root``, with its plots.

    Parameters
    ----------
    root : pathlib.Path
        The data folder (``microtribometer_reciprocating/test_data_2.txt`` in it).
    out : pathlib.Path
        Output folder of its plots.
    plots : bool, optional
        Write the PNG plots.

    Returns
    -------
    dict
        The data set's section of the realdata report (held-out RMS per friction model).
    """
    T0 = time.perf_counter()
    path = need_file(Path(root) / "microtribometer_reciprocating" / "test_data_2.txt",
                      "tribometer data (shared/data/microtribometer_reciprocating)")
    d = load_tribometer(path)
    r = identify_tribometer(d)
    r["sha256"] = sha256(path)
    r["readme"] = {"mu_sliding_median": 0.43, "x_zero_m": 0.06e-3, "x_80_m": 0.10e-3}
    r["dataset"] = "microtribometer_reciprocating"
    if plots:
        r["plots"] = _trib_plots(Path(out), d, r)
    r["seconds"] = time.perf_counter() - T0
    return r


def _trib_plots(out: Path, d, r: dict) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    j = r["held_out_strokes"][len(r["held_out_strokes"]) // 2]
    a, b = d.strokes[j]
    a0 = d.strokes[j - 1][0]
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    ax[0].plot(d.x[a0:b] * 1e3, d.f[a0:b], "k.", ms=2, label="measured")
    for k, e in r["models"].items():
        ax[0].plot(d.x[a0:b] * 1e3, e["_pred"][a0:b], lw=1, label=f"{k} (held-out RMS {e['rms_held_N']:.3f} N)")
    ax[0].set_xlabel("position [mm]")
    ax[0].set_ylabel("friction (resisting) [N]")
    ax[0].set_title(f"strokes {j - 1}-{j} (stroke {j} held out)")
    ax[0].legend(fontsize=7)
    s = np.sign(d.x[b - 1] - d.x[a])
    disp = s * (d.x[a:b] - d.x[a]) * 1e3
    ax[1].plot(disp, s * d.f[a:b], "k.", ms=2, label="measured")
    for k, e in r["models"].items():
        ax[1].plot(disp, s * e["_pred"][a:b], lw=1, label=k)
    for xv, lab in ((0.06, "README 0.06 mm"), (0.10, "README 0.10 mm")):
        ax[1].axvline(xv, color="0.6", ls="--", lw=0.8, label=lab)
    ax[1].set_xlabel("displacement since reversal [mm]")
    ax[1].set_ylabel("friction in the new direction [N]")
    ax[1].set_title("transition after a reversal")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    p = outputs.savefig(fig, out / "tribometer_models.png", dpi=90)
    plt.close(fig)
    return [p.name]

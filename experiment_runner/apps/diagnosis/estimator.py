"""The diagnosis as an estimator (scikit-learn style): ``fit``, ``predict``, ``score``.

:class:`Diagnosis` wraps :func:`.pipeline.diagnose` (its stages: predict -> locate ->
propose -> select by the replay -> validate -> report) so that an improved model can be used
and judged like any fitted estimator:

``fit(recording, nominal)``
    runs the diagnosis; sets ``model_`` (the improved :class:`.model.ModelSpec`, the same one
    written as ``improved_preset.yaml``), ``nominal_``, ``effects_`` (keys adopted, in order)
    and ``report_`` (the report dict).
``predict(data)``
    the improved model's noise-free closed-loop replay of ``data``'s held-out trials
    (:class:`.replay_floor.Replay`: command ``u`` [N] and measurement ``y`` [m], (T, B) arrays).
``score(data)``
    the share of the nominal's held-out replay error in excess of the run-to-run floor that
    the improved model removes (1: down to the floor, 0: no better, negative: worse) -- the
    measure the diagnosis adopts effects by (:mod:`.judge`).
"""
from __future__ import annotations

from .controller import controller_check, equivalent_reference
from .data import DiagData, load_data
from .judge import ReplayJudge
from .model import ModelSpec, load_model
from .options import CONTROLLER_TOL, Options
from .pipeline import diagnose
from .replay_floor import Replay

__all__ = ["Diagnosis"]


class Diagnosis:
    """Model diagnosis as an estimator.

    Parameters
    ----------
    **options
        Fields of :class:`.options.Options` (e.g. ``library=LIBRARY.select([...])``, ``effects=[...]``,
        ``plots=False``): ``library`` is the :class:`.effects.Library` the candidates come from.
    """

    def __init__(self, **options):
        self.options = Options(**options)

    def fit(self, recording, nominal, data: DiagData | None = None, out=None) -> "Diagnosis":
        """Diagnose ``recording`` (path / Recording, or ``None`` with ``data``) against ``nominal``.

        Parameters
        ----------
        recording : str, pathlib.Path or Recording
            A contract recording (MCAP file or bag folder); None when ``data`` is given.
        nominal : str, pathlib.Path, dict or ModelSpec
            The model that was supposed to predict it (:func:`.model.load_model`).
        data : DiagData, optional
            The recording already loaded.
        out : str or pathlib.Path, optional
            Output folder of the report.

        Returns
        -------
        Diagnosis
            ``self``, with ``model_``, ``report_``, ``nominal_``, ``effects_``.
        """
        rep = diagnose(recording, nominal, out=out, options=self.options, data=data)
        self.model_: ModelSpec = rep.pop("_improved_spec")
        self.report_ = rep
        self.nominal_ = load_model(nominal)
        self.effects_ = [f["effect"] for f in rep["found"]]
        return self

    def _judge(self, data) -> ReplayJudge:
        if not isinstance(data, DiagData):
            data = load_data(data)
        spec = self.nominal_
        if abs(spec.preset.controller.rate - data.rate) > 1e-3 * data.rate:
            spec = spec.with_changes({"controller.rate": float(data.rate)})
        x_eq = equivalent_reference(spec, data) if controller_check(spec, data) > CONTROLLER_TOL else None
        return ReplayJudge(data, x_ref=x_eq)

    def predict(self, data) -> Replay:
        """Closed-loop replay of the held-out trials of ``data`` (DiagData or recording) by ``model_``.

        Parameters
        ----------
        data : DiagData, str or pathlib.Path
            Data (or a recording) with held-out trials.

        Returns
        -------
        Replay
            Command [N] and position [m], (T, B) each.
        """
        return self._judge(data).replay(self._rated(self.model_, data))

    def score(self, data) -> float:
        """Share of the nominal's replay excess over the floor removed by ``model_`` on ``data``.

        Parameters
        ----------
        data : DiagData, str or pathlib.Path
            Data (or a recording) with held-out trials.

        Returns
        -------
        float
            1: the improved model replays at its floor; 0: no better than the nominal; < 0: worse.
        """
        j = self._judge(data)
        nom, new = j.floor(self._rated(self.nominal_, data)), j.floor(self._rated(self.model_, data))
        r_nom, r_new = j.floor_ratio(nom.replay, nom), j.floor_ratio(new.replay, new)
        if r_nom <= 1.0:
            return 1.0 if r_new <= 1.0 else 1.0 - (r_new - 1.0)
        return 1.0 - max(r_new - 1.0, 0.0) / (r_nom - 1.0)

    @staticmethod
    def _rated(spec: ModelSpec, data) -> ModelSpec:
        rate = data.rate if isinstance(data, DiagData) else None
        if rate is not None and abs(spec.preset.controller.rate - rate) > 1e-3 * rate:
            return spec.with_changes({"controller.rate": float(rate)})
        return spec

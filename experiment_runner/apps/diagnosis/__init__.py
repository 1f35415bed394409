"""Model diagnosis: where a recording and its nominal model disagree, which physics is
missing, its fitted parameters, and the held-out proof (issue 5).

Pipeline (:func:`.pipeline.diagnose`, stages in :mod:`.stages`): predict (:mod:`.predict`,
:mod:`.observer`: closed-loop replay, force observer, open-loop windows, noise floor) -> locate
(:mod:`.locate`) -> name (:mod:`.effects`, the effect library) -> fit and choose (:mod:`.fit`,
:mod:`.forward`: the forward selection, decided by the replay judge of :mod:`.judge`) -> show
(:mod:`.verdict`, :mod:`.report`). :mod:`.synth` makes concealed-truth recordings; :mod:`.selftest`
and :mod:`.power` prove the chain on them. Command line: :mod:`.cli`.
"""
from .cli import add_diagnose_arguments, main_diagnose
from .synth import add_synth_arguments, main_synth

__all__ = ["add_diagnose_arguments", "main_diagnose", "add_synth_arguments", "main_synth"]

"""Power study: ``nanostage diagnose --selftest --power [--cases N] [--json]``.

Randomized concealed-effect cases instead of a fixed list: :mod:`.cases` deals them, each from a
seed fixed by its index (same study, same cases); :mod:`.case_run` builds one case's nominal,
concealed truth and recording, diagnoses it and judges the outcome; :mod:`.study` runs the cases,
computes the rates and writes the report.
"""

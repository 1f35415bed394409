"""Docs as reference: numpydoc validation of ``diagnosis`` and ``campaigns``, and ruff over the repo.

The numpydoc check walks every public module, class, function and method of
:mod:`experiment_runner.apps.diagnosis` and :mod:`experiment_runner.apps.campaigns` (public: no leading
underscore in the name or in any package on its path, and defined in that module, not imported
into it) and runs :func:`numpydoc.validate.validate` on it, keeping the codes in :data:`CHECKS`.
A method without a docstring of its own that overrides a documented method of a base class
inherits that contract (one home per concept: the base class documents the interface once).
A module is checked for a docstring only: its text is free prose. A pydantic model's field
documented by its ``Field(description=...)`` (the schema's own home for it, what
``model_json_schema()`` shows) counts as a documented parameter.

``test/docs_baseline.txt`` lists the findings that were there when the check came in, one
``object CODE`` a line. The check fails on any finding not in it (new code is documented) and on
any line in it that no longer fails (document an object, then delete its line): the list only
shrinks.

The ruff check runs ``ruff check`` over the repository with the rule set stated in ``ruff.toml``.
"""
from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BASELINE = Path(__file__).with_name("docs_baseline.txt")
PACKAGES = ("experiment_runner.apps.diagnosis", "experiment_runner.apps.campaigns")

#: numpydoc codes checked, and why. Not checked, deliberately: wording and layout (SS02-SS06,
#: GL01-GL03, PR05-PR10, RT02-RT05), and sections numpydoc wants everywhere that would only be
#: filler on a small helper (ES01 extended summary, SA01 See Also, EX01 Examples: examples are
#: written where they are cheap and then run as doctests).
CHECKS = {
    "GL08": "every public object has a docstring",
    "SS01": "the docstring opens with a one-line summary",
    "GL06": "no unknown section (a misspelt 'Parameters' hides the parameters from the other checks)",
    "PR01": "every parameter is documented",
    "PR02": "no documented parameter that the signature does not have",
    "PR04": "every documented parameter has a type (a type hint on the signature counts as one)",
    "RT01": "a function that returns a value says what it returns (Returns section)",
}


def _function(attr):
    """The function behind a class attribute (method, classmethod, staticmethod, property)."""
    if isinstance(attr, property):
        return attr.fget
    return getattr(attr, "__func__", attr)


def _inherits_doc(cls, name, attr) -> bool:
    """True when ``cls.name`` has no docstring of its own and overrides a documented base method."""
    if getattr(_function(attr), "__doc__", None):
        return False
    for base in cls.__mro__[1:]:
        if name in vars(base):
            return bool(getattr(_function(vars(base)[name]), "__doc__", None))
    return False


def public_objects():
    """Yield ``(qualified name, object)`` for every public object of :data:`PACKAGES`."""
    for package in PACKAGES:
        root = importlib.import_module(package)
        names = [package] + [m.name for m in pkgutil.walk_packages(root.__path__, package + ".")]
        for modname in names:
            if any(part.startswith("_") for part in modname.split(".")):
                continue
            module = importlib.import_module(modname)
            yield modname, module
            for name, obj in vars(module).items():
                if name.startswith("_") or getattr(obj, "__module__", None) != modname:
                    continue
                if inspect.isclass(obj):
                    yield f"{modname}.{name}", obj
                    for an, attr in vars(obj).items():
                        f = _function(attr)
                        if an.startswith("_") or not (inspect.isfunction(f) or isinstance(attr, property)):
                            continue
                        if not _inherits_doc(obj, an, attr):
                            yield f"{modname}.{name}.{an}", attr
                elif inspect.isfunction(obj) or hasattr(obj, "py_func"):  # numba dispatchers too
                    yield f"{modname}.{name}", obj


def _annotated(obj, param: str) -> bool:
    """True when parameter ``param`` of ``obj`` (a function or class) carries a type hint."""
    try:
        sig = inspect.signature(_function(obj))
    except (TypeError, ValueError):
        return False
    p = sig.parameters.get(param.lstrip("*"))
    return p is not None and p.annotation is not inspect.Parameter.empty


def _described_fields(obj) -> set[str]:
    """Fields of a pydantic model documented by ``Field(description=...)`` (empty for anything else)."""
    fields = getattr(obj, "model_fields", None) if inspect.isclass(obj) else None
    return {n for n, f in (fields or {}).items() if getattr(f, "description", None)}


def findings() -> set[str]:
    """Every ``"object CODE"`` that numpydoc validation reports for a code in :data:`CHECKS`."""
    from numpydoc.validate import validate

    out = set()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpydoc warns on free-form sections of module docstrings
        for qualname, obj in public_objects():
            if inspect.ismodule(obj):
                if not (obj.__doc__ or "").strip():
                    out.add(f"{qualname} GL08")
                continue
            for code, message in validate(qualname)["errors"]:
                if code not in CHECKS:
                    continue
                if code == "PR01":
                    m = re.search(r"Parameters \{(.*)\} not documented", message)
                    missing = set(re.findall(r"'([^']+)'", m.group(1))) if m else {None}
                    if not missing - _described_fields(obj):
                        continue
                if code == "PR04":
                    m = re.search(r'Parameter "([^"]+)"', message)
                    if m and _annotated(obj, m.group(1)):
                        continue
                out.add(f"{qualname} {code}")
    return out


def read_baseline() -> set[str]:
    """The findings accepted when the check came in (``test/docs_baseline.txt``)."""
    lines = BASELINE.read_text().splitlines() if BASELINE.exists() else []
    return {ln.strip() for ln in lines if ln.strip() and not ln.startswith("#")}


@pytest.mark.slow
def test_numpydoc_on_diagnosis_and_campaigns():
    pytest.importorskip("numpydoc", reason="numpydoc is pinned in requirements.txt: run scripts/bootstrap.sh")
    found, accepted = findings(), read_baseline()
    new = sorted(found - accepted)
    fixed = sorted(accepted - found)
    assert not new, (
        "numpydoc finds undocumented public API (document it; codes: "
        + ", ".join(f"{c} {w}" for c, w in CHECKS.items()) + "):\n  " + "\n  ".join(new))
    assert not fixed, (
        f"these lines of {BASELINE.name} no longer fail: delete them so the list only shrinks:\n  "
        + "\n  ".join(fixed))


@pytest.mark.slow  # imports every diagnosis and campaigns module (~6 s)
def test_public_object_walk_sees_methods_and_skips_private():
    """The walk the numpydoc check relies on reaches methods and leaves private names out."""
    names = dict(public_objects())
    assert "experiment_runner.apps.diagnosis" in names
    assert any(n.startswith("experiment_runner.apps.campaigns.") for n in names)
    assert not [n for n in names if any(part.startswith("_") for part in n.split("."))]
    methods = [n for n, o in names.items() if not inspect.ismodule(o) and n.count(".") >= 4
               and inspect.isclass(names.get(n.rsplit(".", 1)[0]))]
    assert methods, "no method reached: the walk would check classes' methods not at all"


def test_ruff_check_passes_over_the_repo():
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "--output-format", "concise", str(ROOT)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert "No module named ruff" not in proc.stderr, "ruff is pinned in requirements.txt: run scripts/bootstrap.sh"
    assert proc.returncode == 0, f"ruff check (rule set in ruff.toml) finds:\n{proc.stdout}{proc.stderr}"


def test_pydantic_field_description_counts_as_documented():
    """The PR01 exception is exactly the fields with a ``Field(description=...)``."""
    from pydantic import BaseModel, Field

    class M(BaseModel):
        a: float = Field(1.0, description="the a [m]")
        b: float = 2.0

    assert _described_fields(M) == {"a"}
    assert _described_fields(M()) == set() and _described_fields(len) == set()

"""API conventions: options are keyword-only, the public surface imports and is documented."""

import inspect

import jaxnm

# Positional defaults that are data rather than options (like gluLookAt's `up`).
ALLOWED_POSITIONAL_DEFAULTS = {
    ("look_at", "up"),
    ("sample", "duvdx"),
    ("sample", "duvdy"),
    ("fit_normal_map", "options"),
}


def _public_functions():
    for name in jaxnm.__all__:
        obj = getattr(jaxnm, name)
        if inspect.isfunction(obj) or callable(obj) and not inspect.isclass(obj):
            yield name, obj


def test_options_are_keyword_only():
    bad = []
    for name, fn in _public_functions():
        sig = inspect.signature(fn)
        for p in sig.parameters.values():
            if (p.kind == p.POSITIONAL_OR_KEYWORD and p.default is not p.empty
                    and (name, p.name) not in ALLOWED_POSITIONAL_DEFAULTS):
                bad.append(f"{name}({p.name}=...)")
    assert not bad, f"optional arguments should be keyword-only: {bad}"


def test_every_public_name_is_documented():
    missing = [n for n in jaxnm.__all__ if not (getattr(jaxnm, n).__doc__ or "").strip()]
    assert not missing, missing


def test_all_is_complete_and_importable():
    assert len(set(jaxnm.__all__)) == len(jaxnm.__all__)
    for n in jaxnm.__all__:
        assert getattr(jaxnm, n) is not None

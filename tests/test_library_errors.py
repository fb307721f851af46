"""Every error the library raises derives from raytun3r_plugin.errors.Raytun3rError.

A scan of the package source (``raytun3r_plugin/`` and ``patches/``): a ``raise`` of a plain
built-in ``ValueError``/``TypeError``/``KeyError``/``RuntimeError`` (or of the bare base class)
fails, so a caller can catch everything raytun3r raises with one ``except Raytun3rError``. The
project's subclasses also derive from the matching built-in, so ``except ValueError`` callers
keep working.
"""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from raytun3r_plugin import errors

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("raytun3r_plugin", "patches")
FORBIDDEN = {"ValueError", "TypeError", "KeyError", "RuntimeError", "Raytun3rError"}
#: (file relative to the repository, exception name) -> why it must stay. Empty today.
ALLOWED: dict[tuple[str, str], str] = {}


def plain_raises(source: str) -> list[tuple[int, str]]:
    """(line, name) of every ``raise X`` / ``raise X(...)`` with X in :data:`FORBIDDEN`."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Raise) or node.exc is None:
            continue
        target = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
        if isinstance(target, ast.Name) and target.id in FORBIDDEN:
            found.append((node.lineno, target.id))
    return sorted(found)


def test_the_scan_finds_plain_raises():
    snippet = "def f(x):\n    if x:\n        raise ValueError('no')\n    raise KeyError\n\ndef g():\n    raise InputError('fine')\n"
    assert plain_raises(snippet) == [(3, "ValueError"), (4, "KeyError")]


def test_the_library_raises_only_raytun3r_errors():
    offenders = []
    files = [path for folder in SOURCES for path in sorted((ROOT / folder).rglob("*.py"))]
    assert len(files) > 40  # the scan really read the package
    for path in files:
        relative = path.relative_to(ROOT).as_posix()
        if relative == "raytun3r_plugin/errors.py":
            continue
        for line, name in plain_raises(path.read_text(encoding="utf-8")):
            if (relative, name) not in ALLOWED:
                offenders.append(f"{relative}:{line}: raise {name}")
    assert not offenders, "raise a raytun3r_plugin.errors subclass instead:\n" + "\n".join(
        offenders
    )


@pytest.mark.parametrize(
    "name",
    [
        n
        for n, c in vars(errors).items()
        if inspect.isclass(c) and issubclass(c, Exception) and c is not errors.Raytun3rError
    ],
)
def test_every_error_class_derives_from_the_base(name):
    assert issubclass(getattr(errors, name), errors.Raytun3rError)


def test_camera_model_errors_are_still_type_errors():
    from raytun3r_plugin.cameras import Camera

    with pytest.raises(TypeError, match="abstract"):
        Camera(10, 10, [1.0, 1.0, 4.5, 4.5])
    assert issubclass(errors.CameraModelError, errors.CameraError)

"""The package keeps its layers: the core never imports the applications.

``raytun3r_plugin.apps`` (command line, demo, benchmark, evaluation, inference-to-files, exporters)
sits on top of the core. If a core module imported from it, ``import raytun3r_plugin.patching``
would drag in argparse front ends and benchmark tables, and a cycle would be one edit away. The
check reads the source with ``ast`` instead of importing it, so it also sees imports inside
functions (the lazy ones) and needs none of the optional dependencies.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).parent.parent
PACKAGE = "raytun3r_plugin"
APPS = f"{PACKAGE}.apps"
#: The method (online adaptation) never imports a baseline: what they share (the virtual pinhole
#: views) lives in the core, ``raytun3r_plugin.pinhole_views``.
METHOD = f"{PACKAGE}.adaptation"
BASELINES = f"{PACKAGE}.baselines"
#: The adapter file format sits below the method and the applications: it may import only these
#: (the camera it carries, the registry for the backbone's description, the safe readers).
ADAPTER_ALLOWED = {
    "errors",
    "atomic_files",
    "_strict",
    "_version",
    "registry",
    "cameras",
    "adapter",
}

#: What a backbone patch may import from the package (docs/adding_a_backbone.md): the hook and
#: registry machinery, the prediction type, weight loading, errors and RoPE, plus ``poses`` (leaf
#: rigid-transform helpers Pi3 re-exports), ``_layout`` (the split-install guard in
#: ``patches/__init__.py``) and the other patch modules. Anything else (adaptation, cameras,
#: apps) would make a backbone depend on code that depends on the backbones.
PATCH_ALLOWED = {
    "hooks",
    "registry",
    "prediction",
    "weights",
    "errors",
    "rope",
    "poses",
    "_layout",
    "patches",
}


def _module_name(path: Path, root: Path) -> tuple[str, bool]:
    """Dotted name of a source file and whether it is a package ``__init__``; ``patches/`` is
    installed as ``raytun3r_plugin.patches``, so it is named that way here too."""
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[0] == "patches":
        parts = [PACKAGE, *parts]
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join(parts), is_package


def imported_modules(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    """Every module an ``import`` or ``from ... import`` statement names, absolute, with its line.

    ``from X import name`` yields both ``X`` and ``X.name``: ``name`` may be a submodule
    (``from raytun3r_plugin import apps``), and the extra candidate costs nothing when it is not.
    """
    package_parts = module.split(".") if is_package else module.split(".")[:-1]
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package_parts[: len(package_parts) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found.append((node.lineno, target))
            found += [(node.lineno, f"{target}.{alias.name}") for alias in node.names]
    return found


def _is_within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def _names_submodules(path: Path, root: Path, line: int) -> bool:
    """Whether every name of the ``from raytun3r_plugin import ...`` statement on ``line`` is a
    submodule (``from raytun3r_plugin import cameras``), not a name the root defines."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.lineno == line and node.module == PACKAGE:
            return all(
                (root / PACKAGE / alias.name).is_dir()
                or (root / PACKAGE / f"{alias.name}.py").is_file()
                for alias in node.names
            )
    return True


def layering_violations(root: Path) -> list[str]:
    """``file:line: message`` for each import that breaks the layers, over the package and ``patches/``."""
    problems: list[str] = []
    sources = sorted((root / PACKAGE).rglob("*.py")) + sorted((root / "patches").rglob("*.py"))
    for path in sources:
        module, is_package = _module_name(path, root)
        if _is_within(module, APPS):
            continue  # the applications may import anything in the core
        is_patch = _is_within(module, f"{PACKAGE}.patches")
        reported: set[int] = set()  # one message per statement, not one per candidate name
        for line, name in imported_modules(path.read_text(encoding="utf-8"), module, is_package):
            if line in reported:
                continue
            where = f"{path.relative_to(root)}:{line}"
            if _is_within(name, APPS):
                problems.append(
                    f"{where}: core module {module} imports the application module {name}"
                )
                reported.add(line)
            elif name == PACKAGE and not _names_submodules(path, root, line):
                # The package root imports everything: a core module that needs a name from it
                # (e.g. ``__version__``) runs an arrow back up; import it from its own module.
                problems.append(f"{where}: core module {module} imports the package root")
                reported.add(line)
            elif (
                module == f"{PACKAGE}.adapter"
                and _is_within(name, PACKAGE)
                and name != PACKAGE
                and name.split(".")[1] not in ADAPTER_ALLOWED
            ):
                problems.append(f"{where}: the adapter file format imports {name}, above it")
                reported.add(line)
            elif _is_within(module, METHOD) and _is_within(name, BASELINES):
                problems.append(
                    f"{where}: the method's module {module} imports the baseline {name}"
                )
                reported.add(line)
            elif is_patch and _is_within(name, PACKAGE) and name != PACKAGE:
                first = name.split(".")[1]
                if first not in PATCH_ALLOWED:
                    problems.append(
                        f"{where}: patch module {module} imports {name} (allowed: {sorted(PATCH_ALLOWED)})"
                    )
                    reported.add(line)
    return problems


def test_core_and_patches_never_import_the_applications():
    problems = layering_violations(ROOT)
    assert not problems, "layering broken:\n" + "\n".join(problems)


def test_the_scan_sees_every_import_form(tmp_path):
    """The checker itself: each way of spelling an import of ``apps`` is reported with its line,
    so the real test above cannot pass merely because the scan misses a form."""
    core = tmp_path / PACKAGE
    (core / "apps").mkdir(parents=True)
    (core / "__init__.py").write_text("")
    (core / "apps" / "__init__.py").write_text("from raytun3r_plugin import geometry\n")  # allowed
    (core / "apps" / "cli.py").write_text("")
    (core / "bad_absolute.py").write_text("import os\nimport raytun3r_plugin.apps.cli\n")
    (core / "bad_from.py").write_text("def f():\n    from raytun3r_plugin.apps.cli import main\n")
    (core / "bad_name.py").write_text("from raytun3r_plugin import apps\n")
    (core / "bad_relative.py").write_text("from .apps import cli\n")
    (core / "good.py").write_text("from raytun3r_plugin import geometry\nfrom . import hooks\n")
    (core / "adapter.py").write_text(
        "from raytun3r_plugin import errors\nfrom raytun3r_plugin.adaptation import losses\n"
    )
    for leaf in ("errors", "geometry", "hooks", "pinhole_views"):
        (core / f"{leaf}.py").write_text("")
    (core / "root_name.py").write_text("from raytun3r_plugin import __version__\n")
    (core / "adaptation").mkdir()
    (core / "adaptation" / "bad_method.py").write_text(
        "from raytun3r_plugin import pinhole_views\nfrom raytun3r_plugin.baselines import lora\n"
    )
    (tmp_path / "patches").mkdir()
    (tmp_path / "patches" / "bad_patch.py").write_text(
        "from raytun3r_plugin import hooks\nfrom ..adaptation import train\n"
    )

    problems = layering_violations(tmp_path)
    assert [p.split(": ")[0] for p in problems] == [
        "raytun3r_plugin/adaptation/bad_method.py:2",
        "raytun3r_plugin/adapter.py:2",
        "raytun3r_plugin/bad_absolute.py:2",
        "raytun3r_plugin/bad_from.py:2",
        "raytun3r_plugin/bad_name.py:1",
        "raytun3r_plugin/bad_relative.py:1",
        "raytun3r_plugin/root_name.py:1",
        "patches/bad_patch.py:2",
    ], problems


def test_the_applications_import_each_other_without_a_circle():
    """``apps`` modules may import one another, but never in a circle (the demo imports the
    benchmark's tables; the fit settings both use live in ``apps/fits.py``)."""
    graph: dict[str, set[str]] = {}
    for path in sorted((ROOT / PACKAGE / "apps").glob("*.py")):
        module, is_package = _module_name(path, ROOT)
        names = imported_modules(path.read_text(encoding="utf-8"), module, is_package)
        graph[module] = {name for _, name in names if _is_within(name, APPS) and name != APPS}
    graph = {m: {n for n in deps if n in graph and n != m} for m, deps in graph.items()}

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        for nxt in graph[start] - seen:
            if nxt == goal or reaches(nxt, goal, seen | {nxt}):
                return True
        return False

    circles = sorted(m for m in graph if reaches(m, m, set()))
    assert not circles, f"import circle through {circles}"

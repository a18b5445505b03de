"""The house's layering (DESIGN.md, "The house"; issues 15 and 45): every import of every module —
at the top or inside a function — points down the arrows

    pipeline/core  <-  pipeline/errors, settings  <-  pipeline/io, raycast, board, workdir, ...
                   <-  stages/, calib/, synth  <-  report  <-  runner  <-  batch, commands/  <-  cli

pipeline/core imports only the standard library, NumPy, SciPy and nlopt (optimisers); errors and settings import only
core and each other.  Within a layer an import is sideways, and a break too: between two stages,
between stages, calib and synth, and between batch and the commands — except inside one package
(a stage's package, stages/<name>/, is one unit with its modules; no name-based folding).  The
report reads files and imports no stage.  No import cycle, anywhere in the project.

KNOWN_BREAKS lists the edges that still break the layering (issue 45 is fixing them): a new
edge fails this test, and so does a listed edge that is gone (take it off the list).

Imports sit at the top of a module (issue 45 item 3): a project import inside a function says why
it waits, in a ``# lazy: why`` comment (the start-up of a command's ``--help``, a heavy library
needed on one path only, a cycle); LAZY_TO_MEND lists those still without one, as KNOWN_BREAKS does.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).parents[1]
PACKAGES = ("pipeline", "stages", "calib")
CORE_LIBRARIES = {"numpy", "scipy", "nlopt"}

KNOWN_BREAKS: set[tuple[str, str]] = set()  # none left: the report's previews use core.prefilter, not the relight stage
LAZY = "# lazy:"
LAZY_TO_MEND: set[tuple[str, str]] = set()  # (module, imported) inside a function, no reason given: none left


def layer(module: str) -> float | None:
    """The module's rank in the arrows above (0 = core), None for a module outside the project."""
    if module == "pipeline.core" or module.startswith("pipeline.core."):
        return 0
    ranks = {
        "pipeline.errors": 0.5,
        "pipeline.settings": 0.5,
        "stages": 2,
        "calib": 2,
        "pipeline.synth": 2,
        "pipeline.report": 3,
        "pipeline.runner": 4,
        "pipeline.batch": 5,
        "pipeline.commands": 5,
        "pipeline.cli": 6,
    }
    for prefix, rank in ranks.items():
        if module == prefix or module.startswith(prefix + "."):
            return rank
    return 1 if module.split(".")[0] == "pipeline" else None


def unit(module: str) -> str:
    """What a sideways import is measured between: a stage or command with the modules of its
    package (stages.fit.convex -> stages.fit), a calib module, a module of the runner's layer."""
    parts = module.split(".")
    if parts[0] == "stages" or parts[:2] == ["pipeline", "commands"]:
        return ".".join(parts[:2] if parts[0] == "stages" else parts[:3])
    return ".".join(parts[:2]) if parts[0] == "calib" else module


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, root: Path = ROOT) -> set[str]:
    """Every module ``path`` (under ``root``) imports, at the top or inside functions (relative
    imports resolved; ``from package import module`` counts the module)."""
    here = module_name(path, root).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            found.add(module)
            found.update(f"{module}.{a.name}" for a in node.names if f"{module}.{a.name}" in MODULES)
    return found


FILES = sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))
MODULES = {module_name(p) for p in FILES}


def edges() -> set[tuple[str, str]]:
    """(importer, imported) pairs that break the layering."""
    breaks = set()
    for path in FILES:
        importer = module_name(path)
        low = layer(importer)
        for imported in imports(path):
            if imported in ("pipeline", "stages", "calib") or imported == importer:
                continue
            rank = layer(imported)
            if low == 0 and rank is None and imported.split(".")[0] not in CORE_LIBRARIES | set(sys.stdlib_module_names):
                breaks.add((importer, imported))  # core imports a library
            elif rank is not None and (rank > low or (rank == low and low in (2, 5) and unit(imported) != unit(importer))):
                breaks.add((importer, imported))  # up, or sideways
            elif layer(importer) == 3 and imported.split(".")[0] == "stages":
                breaks.add((importer, imported))  # the report reads files, not stages
    return breaks


def test_imports_follow_the_layering():
    """Every import points down DESIGN.md's arrows, or is a listed known break."""
    found = edges()
    new = sorted(found - KNOWN_BREAKS)
    assert not new, f"imports against DESIGN.md's layering: {new}"
    fixed = sorted(KNOWN_BREAKS - found)
    assert not fixed, f"fixed, take them off KNOWN_BREAKS: {fixed}"


def cycles(graph: dict[str, list[str]] | None = None) -> list[list[str]]:
    """The import cycles of ``graph`` (module -> the modules it imports; default: the project's):
    strongly connected groups of two or more modules (Tarjan)."""
    if graph is None:
        graph = {module_name(p): sorted(m for m in imports(p) if m in MODULES and m != module_name(p)) for p in FILES}
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, []):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles():
    """No two project modules import each other, directly or through others (a cycle is hidden from
    the arrows when both sit in one unit)."""
    assert cycles() == []


def test_a_package_is_one_unit_and_its_cycles_still_fail():
    """The checker itself: a stage's or a command's package is one unit (its modules import each other
    sideways freely: stages/poses/, pipeline/commands/bench/), but two of its modules importing each
    other are a cycle."""
    assert unit("stages.poses.board") == unit("stages.poses") == "stages.poses" != unit("stages.samples")
    assert unit("pipeline.commands.bench.fit") == unit("pipeline.commands.bench") == "pipeline.commands.bench"
    assert unit("pipeline.commands.bench") != unit("pipeline.commands.synth")
    inside = {"stages.poses.board": ["stages.poses.colmap"], "stages.poses.colmap": ["stages.poses.board"]}
    assert cycles(inside) == [["stages.poses.board", "stages.poses.colmap"]]


def test_the_checker_sees_imports_inside_functions_and_relative_ones(tmp_path):
    """The checker itself: an import inside a function and a relative one are found."""
    probe = tmp_path / "pipeline" / "core" / "probe.py"
    probe.parent.mkdir(parents=True)
    probe.write_text("from . import sh\ndef f():\n    from pipeline.io.images import read_image\n    import trimesh\n")
    assert imports(probe, tmp_path) == {"pipeline.core", "pipeline.core.sh", "pipeline.io.images", "trimesh"}


def unexplained_lazy_imports(path: Path, root: Path = ROOT) -> set[tuple[str, str]]:
    """(module, imported module) of each project import inside a function of ``path`` (under ``root``)
    that gives no reason: no LAZY comment on its own line(s), nor on the comment line directly above
    the run of import lines it belongs to (one comment may explain a block of imports)."""
    here = module_name(path, root)
    package = here.split(".") if path.name == "__init__.py" else here.split(".")[:-1]
    lines = path.read_text().split("\n")
    found = set()
    for fn in ast.walk(ast.parse("\n".join(lines), str(path))):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names if a.name.split(".")[0] in PACKAGES]
            elif isinstance(node, ast.ImportFrom):
                base = package[: len(package) - node.level + 1] if node.level else []
                module = ".".join(base + ([node.module] if node.module else []))
                names = [module] if module.split(".")[0] in PACKAGES else []
            else:
                continue
            if not names or any(LAZY in line for line in lines[node.lineno - 1 : node.end_lineno]):
                continue
            above = node.lineno - 2
            while above >= 0 and lines[above].lstrip().startswith(("from ", "import ")):
                above -= 1
            if above < 0 or not lines[above].lstrip().startswith(LAZY):
                found.update((here, name) for name in names)
    return found


def test_imports_inside_functions_say_why():
    """Every project import inside a function carries a ``# lazy: why`` comment (imports belong at the
    top of the module otherwise), or is a listed one still to mend; a listed one that is gone fails too."""
    found = set().union(*(unexplained_lazy_imports(p) for p in FILES))
    new = sorted(found - LAZY_TO_MEND)
    assert not new, f"imports inside functions without a '{LAZY} why' comment (move them to the top): {new}"
    fixed = sorted(LAZY_TO_MEND - found)
    assert not fixed, f"fixed, take them off LAZY_TO_MEND: {fixed}"


def test_the_lazy_import_checker_fails_on_an_unexplained_one(tmp_path):
    """The checker itself: an import inside a function without a reason is found (a relative one
    too); one under a LAZY comment (a block of them) or with it on its line is not, and neither
    are imports at the top or of other libraries."""
    probe = tmp_path / "pipeline" / "io" / "probe.py"
    probe.parent.mkdir(parents=True)
    probe.write_text(
        "from pipeline.core import sh\n"
        "def f():\n"
        "    import json\n"
        "    from pipeline.core.camera import look_at\n"
        "    from . import images\n"
        "def g():\n"
        f"    {LAZY} SciPy for one command\n"
        "    from pipeline.core.transfer import irradiance_envmap\n"
        "    from pipeline.io.brdf import read_brdf\n"
        f"    from pipeline.synth import make_capture  {LAZY} the renderer\n"
    )
    assert unexplained_lazy_imports(probe, tmp_path) == {
        ("pipeline.io.probe", "pipeline.core.camera"),
        ("pipeline.io.probe", "pipeline.io"),
    }

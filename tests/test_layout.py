"""The tree reads as the data flow and the import graph stays clean: no cycles inside msk_core (lazy imports inside
functions included), msk_core imports no I/O framework and draws nothing (no tqdm, no matplotlib), drivers/ stands
alone, nothing imports upward."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IO_FRAMEWORKS = ("zenoh", "mcap", "serial", "usb", "mcap_protobuf")
# the science layer computes; what people look at (plots, progress bars) is drawn in services/
PRESENTATION = ("tqdm", "matplotlib")
DRIVERS_MAY_IMPORT = ("msk_core.errors", "msk_core.units")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module this file imports, at any depth (imports inside functions count)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def _graph(package: str) -> dict[str, set[str]]:
    files = {_module_name(p): p for p in (ROOT / package).rglob("*.py")}
    return {name: {m for m in _imports(path) if m in files and m != name} for name, path in files.items()}


def test_msk_core_has_no_import_cycles():
    graph = _graph("msk_core")
    # a package's __init__ re-exporting its modules is not a cycle through them
    graph = {m: {d for d in deps if not m.startswith(d + ".")} for m, deps in graph.items()}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for dep in sorted(graph[node]):
            if state.get(dep) == 1:
                cycles.append(stack[stack.index(dep) :] + [dep])
            elif dep not in state:
                visit(dep, stack + [dep])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert not cycles, f"import cycles in msk_core: {cycles}"


def test_msk_core_imports_no_io_or_presentation_framework_and_drivers_stand_alone():
    for path in (ROOT / "msk_core").rglob("*.py"):
        bad = {m for m in _imports(path) if m.split(".")[0] in IO_FRAMEWORKS + PRESENTATION + ("services", "drivers")}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"
    for path in (ROOT / "drivers").rglob("*.py"):
        # the shared exception hierarchy and physical constants (two leaf modules) are what drivers take from msk_core
        bad = {
            m
            for m in _imports(path)
            if m.split(".")[0] in ("services", "msk_core") and not m.startswith(DRIVERS_MAY_IMPORT)
        }
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


def test_what_drivers_take_from_msk_core_are_leaves():
    # a leaf imports nothing of the project, so drivers taking it still pull in no science code
    for module in DRIVERS_MAY_IMPORT:
        path = ROOT / (module.replace(".", "/") + ".py")
        inner = {m for m in _imports(path) if m.split(".")[0] in ("msk_core", "services", "drivers")}
        assert not inner, f"{path.relative_to(ROOT)} imports {sorted(inner)}"


def test_one_gravity():
    # GRAVITY = 9.81 is defined once (msk_core.units); a second definition or a literal 9.81 would drift from it
    definitions, literals = [], []
    for package in ("msk_core", "services", "drivers"):
        for path in (ROOT / package).rglob("*.py"):
            where = str(path.relative_to(ROOT))
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                if isinstance(node, ast.Assign) and any(
                    isinstance(t, ast.Name) and t.id == "GRAVITY" for t in node.targets
                ):
                    definitions.append(f"{where}:{node.lineno}")
                elif isinstance(node, ast.Constant) and node.value == 9.81 and where != "msk_core/units.py":
                    literals.append(f"{where}:{node.lineno}")
    assert len(definitions) == 1 and definitions[0].startswith("msk_core/units.py:"), definitions
    assert not literals, f"9.81 written out instead of msk_core.units.GRAVITY: {literals}"


def test_the_tree_has_a_room_per_stage_and_its_root_only_what_every_stage_shares():
    for room in ("model", "signal", "imu", "estimate", "io", "synth"):
        assert (ROOT / "msk_core" / room / "__init__.py").is_file(), room
    # a module at the root is an error type, a constant or the progress callback every stage uses, never a second
    # name for a stage's module (each concept is imported from one place)
    shared = {"__init__", "errors", "units", "progress"}
    root = {p.stem for p in (ROOT / "msk_core").glob("*.py")}
    assert root == shared, f"msk_core/ root: unexpected {sorted(root - shared)}, missing {sorted(shared - root)}"


# services/ in data-flow order: a room imports only from rooms before it (lazy imports inside functions included)
SERVICE_ROOMS = ("transport", "nodes", "sessions", "surfaces")
# the one upward edge, on purpose: the demo ends by writing its report (a file writer, no live surface)
SERVICE_UPWARD_ALLOWED = {("services.sessions.demo", "services.surfaces.reports.demo")}


def test_services_has_a_room_per_kind_and_each_imports_only_rooms_before_it():
    for room in SERVICE_ROOMS:
        assert (ROOT / "services" / room / "__init__.py").is_file(), room
    # beside the rooms: the command line (cli.py, commands/) and the benchmarks, which may use every room
    root = {p.name for p in (ROOT / "services").iterdir() if p.name not in ("__pycache__", "py.typed")}
    expected = {"__init__.py", "cli.py", "commands", "bench", *SERVICE_ROOMS}
    assert root == expected, f"services/ root: unexpected {sorted(root - expected)}, missing {sorted(expected - root)}"
    upward = []
    for rank, room in enumerate(SERVICE_ROOMS):
        later = tuple(f"services.{r}" for r in SERVICE_ROOMS[rank + 1 :]) + ("services.commands", "services.bench")
        for path in (ROOT / "services" / room).rglob("*.py"):
            module = _module_name(path)
            for imported in _imports(path):
                allowed = any(module == m and imported.startswith(t) for m, t in SERVICE_UPWARD_ALLOWED)
                if (imported.startswith(later) or imported == "services.cli") and not allowed:
                    upward.append((module, imported))
    assert not upward, f"imports against the data flow (transport < nodes < sessions < surfaces): {sorted(upward)}"


MAX_FUNCTION_LINES = 80
# the compiled per-frame model evaluation: one numba kernel per call, kept whole on purpose (no Python-level calls)
NUMBA_KERNEL_MODULES = ("msk_core/model/kernels.py",)
NUMBA_DECORATORS = {"_jit", "njit", "jit", "numba.njit", "numba.jit"}
# Functions still over MAX_FUNCTION_LINES lines (``def`` line to last line, decorators not counted), with their
# length when the list was taken (26 Nov, issue 28; empty since 27 Nov, every one split). The list only shrinks: a
# listed function may not grow, a new one may not join it, and one that has been split must leave it.
LONG_FUNCTIONS: dict[str, int] = {}


@functools.lru_cache(maxsize=1)
def _function_lengths() -> dict[str, int]:
    """``path:Class.function`` (nested functions as ``outer.inner``) -> lines, for every function outside the numba
    kernels of msk_core, services and drivers."""
    lengths: dict[str, int] = {}

    def visit(node: ast.AST, where: str, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                visit(child, where, f"{prefix}{child.name}.")
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                decorators = {ast.unparse(d.func if isinstance(d, ast.Call) else d) for d in child.decorator_list}
                if not (where in NUMBA_KERNEL_MODULES and decorators & NUMBA_DECORATORS):
                    lengths[f"{where}:{prefix}{child.name}"] = (child.end_lineno or child.lineno) - child.lineno + 1
                visit(child, where, f"{prefix}{child.name}.")
            else:
                visit(child, where, prefix)

    for package in ("msk_core", "services", "drivers"):
        for path in sorted((ROOT / package).rglob("*.py")):
            where = str(path.relative_to(ROOT))
            visit(ast.parse(path.read_text(), filename=where), where, "")
    return lengths


def test_no_function_over_80_lines_outside_numba_kernels():
    lengths = _function_lengths()
    problems = []
    for name, lines in sorted(lengths.items()):
        if lines > MAX_FUNCTION_LINES and name not in LONG_FUNCTIONS:
            problems.append(f"{name} is {lines} lines (at most {MAX_FUNCTION_LINES}): split it")
        elif name in LONG_FUNCTIONS and lines > LONG_FUNCTIONS[name]:
            problems.append(f"{name} grew from {LONG_FUNCTIONS[name]} to {lines} lines: split it")
    for name, listed in sorted(LONG_FUNCTIONS.items()):
        if lengths.get(name, 0) <= MAX_FUNCTION_LINES:
            now = f"{lengths[name]} lines" if name in lengths else "gone"
            problems.append(f"{name} (listed at {listed} lines) is now {now}: remove it from LONG_FUNCTIONS")
    assert not problems, "\n".join(problems)


def test_the_function_length_rule_sees_long_functions_and_exempts_only_numba_kernels():
    lengths = _function_lengths()
    assert lengths["msk_core/model/pack.py:ModelPack.__init__"] > 5  # methods are found, by class
    assert "msk_core/model/kernels.py:rigid_torques" not in lengths  # the numba kernel is exempt ...
    assert "msk_core/estimate/active_set.py:solve_box_lsq" in lengths  # ... numba functions elsewhere are not


def test_the_estimate_package_names_resolve_on_first_use():
    """msk_core.estimate imports its names on first use (a page reading flags or the fatigue verdict does not pay for
    the estimator's imports): every name it lists resolves, and nothing else does."""
    import subprocess
    import sys

    import pytest

    import msk_core.estimate as estimate

    assert sorted(estimate.__all__) == sorted(estimate._WHERE)  # noqa: SLF001
    for name in estimate.__all__:
        assert getattr(estimate, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        _ = estimate.Nope  # type: ignore[attr-defined]
    light = "import sys, msk_core.estimate.flags, msk_core.estimate.fatigue_verdict; print('scipy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", light], capture_output=True, text=True, check=True).stdout == "False\n"

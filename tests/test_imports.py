"""The package's imports run one way: no import cycle, at module or function level.

Every ``import`` / ``from ... import`` statement of every module under ``rgbdslam/`` (also those
inside functions, which hide a cycle from Python's import machinery but not from a reader) is an
edge from the module to the module it names; ``from pkg import name`` names ``pkg.name`` when
that is a module. A cycle in that graph fails the test with its modules listed.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "rgbdslam"


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """module -> the package modules it imports (module- and function-level)."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative import
                    pkg = name.split(".") if is_pkg else name.split(".")[:-1]
                    pkg = pkg[: len(pkg) - (node.level - 1)]
                    base = ".".join(pkg + ([base] if base else []))
                for a in node.names:
                    sub = f"{base}.{a.name}"
                    targets.append(sub if sub in modules else base)
            for t in targets:
                if t in modules and t != name:
                    graph[name].add(t)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle as [a, b, ..., a], or None."""
    colour: dict[str, int] = {}  # 1 = on the stack, 2 = done
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        colour[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if colour.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in colour and (c := visit(n)):
                return c
        stack.pop()
        colour[m] = 2
        return None

    for m in sorted(graph):
        if m not in colour and (c := visit(m)):
            return c
    return None


def test_the_walk_sees_function_level_imports_and_finds_a_cycle():
    graph = import_graph()
    # function-level imports count: the SLAM chain builds the loop closer inside __init__
    assert "rgbdslam.loop.detector" in graph["rgbdslam.slam"]
    assert "rgbdslam.posegraph.masat" in graph["rgbdslam.backend.slam_graph"]  # inside a method
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycle_in_the_package():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def folder_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The module graph seen by folder: ``rgbdslam.frontend.features`` is ``frontend``, a top-level
    module (``rgbdslam.slam``) its own node; edges inside one folder are dropped. A stage's config
    section (``rgbdslam.frontend.config``: a dataclass that imports only ``configspec``) belongs to
    the config layer, ``config``, which composes the sections and which the stages import."""
    def folder(m: str) -> str:
        parts = m.split(".")
        if len(parts) == 3 and parts[2] == "config":
            return "config"
        return parts[1] if len(parts) > 1 else parts[0]

    out: dict[str, set[str]] = {}
    for m, deps in graph.items():
        out.setdefault(folder(m), set()).update(folder(d) for d in deps if folder(d) != folder(m))
    return out


def test_folders_import_one_way():
    """No two folders import each other, through any chain: a module may not reach up into a folder
    that imports its own (say ``datasets`` -> ``frontend`` -> ``datasets``), even inside a
    function. The lower folder owns what both need, or the higher one passes a callable in."""
    assert folder_graph({"rgbdslam.a.x": {"rgbdslam.b.y"}, "rgbdslam.b.y": {"rgbdslam.b.z"},
                         "rgbdslam.b.z": {"rgbdslam.a.w"}, "rgbdslam.a.w": set()}) == {"a": {"b"}, "b": {"a"}}
    assert folder_graph({"rgbdslam.config": {"rgbdslam.a.config"}, "rgbdslam.a.config": set(),
                         "rgbdslam.a.x": {"rgbdslam.config"}}) == {"config": set(), "a": {"config"}}
    cycle = find_cycle(folder_graph(import_graph()))
    assert cycle is None, "folder import cycle: " + " -> ".join(cycle)


def test_layers_run_one_way():
    """The offline pose-graph tool never imports the SLAM back end or the front end; the
    evaluation imports neither; pure geometry imports nothing of the stages."""
    graph = import_graph()
    for m, deps in graph.items():
        if m.startswith("rgbdslam.posegraph"):
            assert not any(d.startswith(("rgbdslam.backend", "rgbdslam.frontend", "rgbdslam.loop")) for d in deps), m
        if m.startswith("rgbdslam.evaluation"):
            assert not any(d.startswith(("rgbdslam.backend", "rgbdslam.frontend", "rgbdslam.posegraph")) for d in deps), m
        if m.startswith("rgbdslam.geometry"):
            assert all(d.startswith(("rgbdslam.geometry", "rgbdslam.errors")) for d in deps), (m, deps)


STAGES = ("datasets", "frontend", "stereo", "landmarks", "loop", "backend", "mapping", "viz")
# stage modules that load a run folder's whole configuration (``rgbdslam fuse``)
LOADS_A_RUN_CONFIG = {"rgbdslam.mapping.fusion"}


def runtime_imports_of_config(source: str) -> list[int]:
    """Lines of ``source`` that import ``rgbdslam.config`` when the module runs (an import under
    ``if TYPE_CHECKING:`` names a type for type checkers only and does not count)."""
    tree = ast.parse(source)
    typing_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                   and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"
                   for stmt in node.body for n in ast.walk(stmt)}
    out = []
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom) and node.module == "rgbdslam.config" or \
                isinstance(node, ast.ImportFrom) and node.module == "rgbdslam" and any(a.name == "config" for a in node.names) or \
                isinstance(node, ast.Import) and any(a.name == "rgbdslam.config" for a in node.names):
            out.append(node.lineno)
    return out


def test_the_config_import_check_sees_runtime_imports_only():
    src = ("from typing import TYPE_CHECKING\nfrom rgbdslam.loop.config import LoopConfig\n"
           "if TYPE_CHECKING:\n    from rgbdslam.config import Config\n"
           "def f():\n    from rgbdslam.config import load_config\n    import rgbdslam.config\n"
           "from rgbdslam import config\n")
    assert sorted(runtime_imports_of_config(src)) == [6, 7, 8]


def test_stages_own_their_config_sections():
    """A stage's modules take their section from the stage's own ``config.py``; ``rgbdslam.config``
    (which composes the sections) is above them and never imported by them at run time."""
    bad = {}
    for name, path in _modules().items():
        parts = name.split(".")
        if len(parts) > 2 and parts[1] in STAGES and name not in LOADS_A_RUN_CONFIG:
            if lines := runtime_imports_of_config(path.read_text(encoding="utf-8")):
                bad[name] = lines
    assert not bad, f"import the section from the stage's config.py instead (lines): {bad}"
    graph = import_graph()
    for stage in STAGES:  # each section's module is a leaf: it imports only the declaration markers
        assert graph[f"rgbdslam.{stage}.config"] <= {"rgbdslam.configspec"}, stage

# ----------------------------------------------------------------------------- benchmarks/
BENCHMARKS = PACKAGE.parent / "benchmarks"
TESTS = PACKAGE.parent / "tests"


def benchmark_violations(source: str) -> list[str]:
    """What a benchmark module must not do: import a private name (``from rgbdslam.x import _y``,
    ``import rgbdslam._x``), read one (``module._y``, ``obj._y`` of anything but ``self``/``cls``), write
    one through a keyword argument (``replace(f, _tree=None)``), or
    patch the library at run time (``setattr``/``delattr``, assigning an attribute of a name imported
    from rgbdslam, or an attribute two levels deep such as ``cfg.section.key = ...``)."""
    tree = ast.parse(source)
    imported: set[str] = set()  # names bound to rgbdslam modules, classes and functions
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("rgbdslam"):
            if any(p.startswith("_") for p in node.module.split(".")):
                out.append(f"line {node.lineno}: imports the private module {node.module}")
            for a in node.names:
                if a.name.startswith("_"):
                    out.append(f"line {node.lineno}: imports the private name {a.name} from {node.module}")
                imported.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("rgbdslam"):
                    if any(p.startswith("_") for p in a.name.split(".")):
                        out.append(f"line {node.lineno}: imports the private module {a.name}")
                    imported.add(a.asname or a.name.split(".")[0])
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            if not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                out.append(f"line {node.lineno}: reads the private attribute {node.attr}")
        if isinstance(node, ast.keyword) and node.arg and node.arg.startswith("_"):
            out.append(f"line {node.lineno}: passes the private field {node.arg} as a keyword argument")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("setattr", "delattr"):
            out.append(f"line {node.lineno}: {node.func.id}() (patching at run time)")
        targets = list(node.targets) if isinstance(node, ast.Assign) else \
            [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else []
        while targets:
            a = targets.pop()
            if isinstance(a, (ast.Tuple, ast.List)):
                targets += a.elts
                continue
            while isinstance(a, (ast.Subscript, ast.Starred)):  # x.y[i] = ... changes x.y
                a = a.value
            if isinstance(a, ast.Attribute):
                base = a.value
                if isinstance(base, ast.Name) and base.id in imported:
                    out.append(f"line {node.lineno}: assigns {base.id}.{a.attr} (patching the library)")
                elif isinstance(base, ast.Attribute):
                    out.append(f"line {node.lineno}: assigns .{base.attr}.{a.attr} (another object's state)")
    return out


def test_the_benchmark_check_finds_private_imports_and_patches():
    found = benchmark_violations(
        "import rgbdslam.pipeline as pipeline\nfrom rgbdslam.loop import detector\n"
        "from rgbdslam.posegraph.masat import _edge_variances\nfrom rgbdslam.frontend import features\n"
        "pipeline.track_all = print\nsetattr(detector.LoopCloser, 'detect', print)\ncfg.landmarks.enabled = True\n"
        "x = features._detect\nself._ok = 1\nrow.tracked = 3\nkeep[features.detect(x)] = True\n"
        "g = replace(f, pts=p, _tree=None)\nh = replace(f, pts=p, **extra)\n")
    assert sorted(int(f.split(":")[0][5:]) for f in found) == [3, 5, 6, 7, 8, 12]  # not self._ok, row.tracked, **extra


def test_benchmarks_use_public_names_and_patch_nothing():
    files = sorted(BENCHMARKS.rglob("*.py"))
    assert files, BENCHMARKS
    bad = {str(p.relative_to(PACKAGE.parent)): v for p in files if (v := benchmark_violations(p.read_text()))}
    assert not bad, bad


def test_tests_never_load_code_by_file_path():
    """Benchmarks are imported as the package ``benchmarks``; no test execs a file by its path."""
    bad = [str(p.relative_to(PACKAGE.parent)) for p in TESTS.rglob("*.py")
           if p.name != "test_imports.py" and "spec_from_file_location" in p.read_text()]
    assert not bad, bad

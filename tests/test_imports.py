"""The package's import graph: data flows one way (STYLE.md, "Layout").

Every jaxhead module sits on a floor; a module may import only from its own floor or below, no
module-level import cycle exists, no private name crosses a package border, and function-local
imports are kept for optional or heavy third-party dependencies only.
"""

import ast
import importlib
import pathlib

import pytest

import jaxhead

ROOT = pathlib.Path(jaxhead.__file__).parent

#: Floors, bottom first: types and files, then the stages in pipeline order, then runs, then the CLI.
FLOORS = [
    {"_types", "_files", "_tables", "tissue"},
    {"volume", "masks"},
    {"phantom"},
    {"segmentation"},
    {"geometry"},
    {"io"},
    {"electrodes", "protocol"},
    {"fem"},
    {"inverse"},
    {"study"},
    {"plot"},
    {"run"},
    {"cli", "__main__", "__init__"},
]
FLOOR = {unit: i for i, units in enumerate(FLOORS) for unit in units}

#: Third-party modules that may be imported inside a function: optional (gmsh, tetgen: copyleft
#: extras; pytetwild, pyvista) or
#: heavy and only needed to draw (matplotlib); the CLI imports jax to set float64 at its entry.
LOCAL_OK = ("matplotlib", "pyvista", "pytetwild", "gmsh", "tetgen", "jax")


def _modules():
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        yield ".".join(("jaxhead", *rel.parts)), path


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _resolve(module: str, path: pathlib.Path, node: ast.ImportFrom) -> str:
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    if node.level > 1:
        package = package[: len(package) - (node.level - 1)]
    return ".".join(package + ([node.module] if node.module else []))


def _imports(module, path):
    """(target module, imported names, at module level?, lineno) of every jaxhead import."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            target = _resolve(module, path, node)
            if node.module is None:  # `from .. import io`: each name is a module
                out += [(f"{target}.{a.name}", [], id(node) in top, node.lineno) for a in node.names]
            else:
                out.append((target, [a.name for a in node.names], id(node) in top, node.lineno))
        elif isinstance(node, ast.Import) and any(a.name.startswith("jaxhead") for a in node.names):
            out.append((node.names[0].name, [], id(node) in top, node.lineno))
    return out


MODULES = dict(_modules())


def test_every_module_is_on_a_floor():
    units = {_unit(m) for m in MODULES}
    assert units <= set(FLOOR), f"modules on no floor: {sorted(units - set(FLOOR))}; add them to FLOORS"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_upward_or_private_imports(module):
    path = MODULES[module]
    for target, names, _, line in _imports(module, path):
        src, dst = _unit(module), _unit(target)
        assert FLOOR[dst] <= FLOOR[src], (
            f"{module}:{line} imports {target}, a later stage ({dst} is above {src}); "
            "move the shared piece down or pass it in as an argument")
        if src != dst:
            private = [n for n in names if n.startswith("_")]
            private += [p for p in target.split(".")[2:] if p.startswith("_")] if dst != "_types" and dst != "_files" else []
            assert not private, f"{module}:{line} imports private {private} of {target}; export a public name"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_local_imports_only_for_optional_dependencies(module):
    tree = ast.parse(MODULES[module].read_text())
    top = {id(n) for n in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) not in top:
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                pytest.fail(f"{module}:{node.lineno}: function-local import of jaxhead.{node.module}")
            name = node.module if isinstance(node, ast.ImportFrom) else node.names[0].name
            assert name.split(".")[0] in LOCAL_OK, (
                f"{module}:{node.lineno}: function-local import of {name}; import it at the top")


def test_no_import_cycles():
    graph = {m: set() for m in MODULES}
    for module, path in MODULES.items():
        for target, names, at_top, _ in _imports(module, path):
            if not at_top:
                continue
            for cand in [target] + [f"{target}.{n}" for n in names]:
                if cand in graph and cand != module:
                    graph[module].add(cand)
                elif f"{cand}.__init__" in graph and f"{cand}.__init__" != module:
                    graph[module].add(f"{cand}.__init__")
    # A package's __init__ importing its own submodules is the usual re-export, not a cycle.
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in graph[m]:
            if n.endswith(".__init__") and m.startswith(n[: -len("__init__")]):
                continue
            if state.get(n) == 1:
                cycle = stack[stack.index(n):] + [n]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_every_module_imports_alone(module):
    if module.endswith("__main__"):
        pytest.skip("runs the CLI")
    importlib.import_module(module.removesuffix(".__init__"))


def test_public_api():
    import jaxhead as jh

    assert callable(jh.segment)
    for name in ("SegmentConfig", "load_config", "run_pipeline", "BlockCG", "Grid", "sigma_per_tet"):
        assert hasattr(jh, name), name
    assert set(jh.__all__) <= set(dir(jh))
    assert not [n for n in jh.__all__ if n.startswith("_")]


def test_result_convention():
    """Every stage with a report: `verb` returns the value, `verb_reported` returns (value, report)."""
    import typing

    import jaxhead as jh

    twins = [n for n in jh.__all__ if n.endswith("_reported")]
    assert {"segment_reported", "make_layers_reported", "extract_surfaces_reported",
            "tetrahedralize_reported"} <= set(twins)
    for name in twins:
        verb = getattr(jh, name.removesuffix("_reported"))
        value = typing.get_type_hints(verb)["return"]
        pair = typing.get_type_hints(getattr(jh, name))["return"]
        assert typing.get_origin(pair) is tuple and typing.get_args(pair)[0] == value, (name, pair, value)

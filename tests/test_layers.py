"""The package's architecture, checked on its source: layers that follow the data flow.

jaxnh's folders are layers, in this order (each may import only from itself and the ones before):

    _base       status codes, small linear algebra, compile options, the compatibility module, files
    _model      Mechanism, profiles, rigid bodies, checks of values against the model
    _equations  formulations (Lagrange, Appell, Substituted) and the maps around a step they need
    _solve      simulate, sensitivities, step-mapped solvers, Runge–Kutta tableaus, diagnoses
    _analysis   linearize, sweep
    identify    fit, experiment design, gradient-based design (jaxnh.design)
    models      the built-in mechanisms and the variator's identification
    _cli        the `jaxnh` command line

The public modules `jaxnh.profiles`, `rigid`, `linalg`, `equations`, `solvers`, `design` and `cli` only
re-export names of one layer's module, and only `jaxnh/__init__.py` imports them.

Checked here, by parsing every module (no import is executed):
* no import goes to a later layer;
* there is no cycle among modules, counting every import, inside functions too;
* an import inside a function (or under `if`/`try`) is only of an optional dependency
  (pandas, matplotlib, xarray), and says so in a comment or is named in `OPTIONAL`;
* private internals of JAX and equinox appear only in `jaxnh/_base/compat.py`;
* a public module that re-exports `from <implementation> import *` lists the same `__all__` as its
  implementation, written out (type checkers need a literal list, so it cannot be copied at run time).
"""

import ast
import pathlib
import re
import sys

import pytest


PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "jaxnh"

LAYERS = ["_base", "_model", "_equations", "_solve", "_analysis", "identify", "models", "_cli"]
FACADES = {
    "jaxnh.profiles": "_model",
    "jaxnh.rigid": "_model",
    "jaxnh.linalg": "_base",
    "jaxnh.equations": "_equations",
    "jaxnh.solvers": "_solve",
    "jaxnh.design": "identify",
    "jaxnh.cli": "_cli",
}
OPTIONAL = ("pandas", "matplotlib", "xarray")


def modules() -> dict[str, pathlib.Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = modules()


def layer(name: str) -> int:
    """The layer index of a module (the package itself is above every layer)."""
    if name == "jaxnh":
        return len(LAYERS)
    if name in FACADES:
        return LAYERS.index(FACADES[name])
    return LAYERS.index(name.split(".")[1])


def imports(name: str):
    """(target module, line, inside a function or block) for each jaxnh import of a module."""
    path = MODULES[name]
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        else:
            continue
        for target in targets:
            yield target, node.lineno, id(node) not in top


def test_every_module_has_a_layer():
    for name in MODULES:
        layer(name)  # raises ValueError for a folder that is not a layer


@pytest.mark.parametrize("name", sorted(MODULES))
def test_imports_go_down(name):
    for target, line, _ in imports(name):
        if not target.startswith("jaxnh"):
            continue
        assert target in MODULES, f"{name}:{line} imports {target}, which does not exist"
        if name != "jaxnh" and name not in FACADES:
            assert target not in FACADES and target != "jaxnh", (
                f"{name}:{line} imports the public module {target}; import its implementation instead"
            )
        assert layer(target) <= layer(name), (
            f"{name}:{line} imports {target}: layer {LAYERS[layer(target)]} is above {LAYERS[layer(name)]}"
        )


@pytest.mark.parametrize("name", sorted(MODULES))
def test_imports_inside_functions_are_optional_dependencies(name):
    source = MODULES[name].read_text().splitlines()
    for target, line, inner in imports(name):
        if not inner or (name == "jaxnh" and "TYPE_CHECKING" in "".join(source[:line])):
            continue
        assert target.split(".")[0] in OPTIONAL, (
            f"{name}:{line} imports {target} inside a function or block; only optional dependencies "
            f"({', '.join(OPTIONAL)}) may be imported there"
        )


def test_no_cycle():
    graph = {n: {t for t, _, _ in imports(n) if t in MODULES and t != n} for n in MODULES}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                cycle = stack[stack.index(m) :] + [m]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    # the package's own __init__ imports everything: start from the leaves' point of view
    for n in sorted(MODULES):
        if n not in state:
            visit(n)


def test_private_internals_only_in_the_compatibility_module():
    pattern = re.compile(r"jax\._src|equinox\._|eqx\._|\._value\b|\._index_to_message|\._name_to_item")
    for name, path in MODULES.items():
        if name == "jaxnh._base.compat":
            continue
        for i, text in enumerate(path.read_text().splitlines(), 1):
            assert not pattern.search(text), f"{name}:{i} uses a private name of JAX or equinox: {text.strip()}"


def reexported_all(path: pathlib.Path) -> str | None:
    """The module whose `__all__` a facade adds to its own (`__all__ += _implementation.__all__`,
    `_implementation` imported by `from package import module as _implementation`), or None."""
    body = ast.parse(path.read_text()).body
    aliases = {
        a.asname: f"{node.module}.{a.name}"
        for node in body
        if isinstance(node, ast.ImportFrom) and node.module
        for a in node.names
        if a.asname
    }
    for node in body:
        if (
            isinstance(node, ast.AugAssign)
            and isinstance(node.target, ast.Name)
            and node.target.id == "__all__"
            and isinstance(node.op, ast.Add)
            and isinstance(node.value, ast.Attribute)
            and node.value.attr == "__all__"
            and isinstance(node.value.value, ast.Name)
        ):
            return aliases.get(node.value.value.id)
    return None


@pytest.mark.parametrize("name", sorted(FACADES))
def test_public_modules_export_the_names_of_their_implementation(name):
    """A facade that star-imports its implementation exports exactly its names, in the one form of
    `__all__` that type checkers follow (so `pyright --strict` sees every public name)."""
    stars = [
        node.module
        for node in ast.parse(MODULES[name].read_text()).body
        if isinstance(node, ast.ImportFrom) and node.module and [a.name for a in node.names] == ["*"]
    ]
    if not stars:  # re-exports names one by one (jaxnh.cli): its __all__ is its own
        return
    assert len(stars) == 1, f"{name} re-exports {stars}: a public module re-exports one implementation module"
    assert reexported_all(MODULES[name]) == stars[0], (
        f"{name}: write `from ... import <module> as _implementation` and `__all__ += _implementation.__all__` "
        f"for the star-imported {stars[0]}"
    )


def test_the_layering_check_can_fail(tmp_path, monkeypatch):
    """The checks above find an upward import and a cycle when there is one."""
    fake = dict(MODULES)
    low = tmp_path / "low.py"
    low.write_text("from jaxnh._cli.main import main\n")
    fake["jaxnh._base.low"] = low
    ring = tmp_path / "ring.py"
    ring.write_text("def f():\n    from jaxnh._base import low\n")
    low.write_text(low.read_text() + "from jaxnh._base import ring\n")
    fake["jaxnh._base.ring"] = ring
    monkeypatch.setattr(sys.modules[__name__], "MODULES", fake)
    with pytest.raises(AssertionError, match="layer _cli is above _base"):
        test_imports_go_down("jaxnh._base.low")
    with pytest.raises(AssertionError, match="inside a function"):
        test_imports_inside_functions_are_optional_dependencies("jaxnh._base.ring")
    with pytest.raises(
        pytest.fail.Exception, match="import cycle: jaxnh._base.low -> jaxnh._base.ring -> jaxnh._base.low"
    ):
        test_no_cycle()


def test_every_required_dependency_is_imported_by_the_package():
    """pyproject's runtime dependencies are the ones jaxnh imports (an unused one belongs to an
    extra: scipy, which only the tests' references use, was required and never imported)."""
    import tomllib

    project = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())["project"]
    required = {re.split(r"[\s\[<>=!~;]", d, maxsplit=1)[0].lower().replace("-", "_") for d in project["dependencies"]}
    imported = set()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported.add(node.module.split(".")[0])
    assert not required - imported, f"required but never imported by jaxnh: {sorted(required - imported)}"

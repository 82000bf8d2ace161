"""The layers of the tree: a module's layer is its top-level folder (docs/architecture.md).

Dependencies run one way::

    core                                            errors, files, units, samples ...
      -> can | estimation                           (never each other)
      -> processor                                  frames -> samples -> model input
      -> diagnosis | control | live | firmware | fleet   (beside each other)
      -> cli                                        (one module per subcommand)

``sim`` (the simulated drive) sits at the edge: it uses ``core`` and ``can`` and only
``cli`` uses it. Neither ``estimation`` nor ``core`` imports an I/O package (python-can,
cantools). No import circle, type-only ones included; only a package's ``__init__``
re-exports; no module reaches into another module's underscore names. No function is
over 150 lines, no module over 1,000 and no module docstring over 35. The table of
docs/architecture.md lists every folder and module of the tree, and no other.

The checks read the source (ast), so they also see imports inside functions.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PKG = SRC / "canrls"
ARCHITECTURE = SRC.parent / "docs" / "architecture.md"

#: the layers, each a top-level folder of canrls, and the layers each may import
_BOTTOM = {"core", "can", "estimation", "processor"}
#: the rooms above the processor: each sees the processor and below, none another
BESIDE = ("diagnosis", "control", "live", "firmware", "fleet")
ALLOWED = {
    "core": {"core"},
    "can": {"core"},
    "estimation": {"core"},
    "processor": _BOTTOM,
    **{room: _BOTTOM for room in BESIDE},
    "sim": {"core", "can"},
    "cli": {*_BOTTOM, *BESIDE, "sim", "cli"},
}
#: the modules outside the layers' folders: the package itself and ``python -m canrls``
ROOT_MODULES = {"canrls": "core", "canrls.__main__": "cli"}
#: third-party I/O packages the pure layers must not import
IO_PACKAGES = {"can", "cantools"}
#: underscore names of the standard library's own protocols (namedtuple, enum)
STD_PRIVATE = {"_replace", "_asdict", "_fields", "_make", "_value_", "_name_", "_missing_",
               "_generate_next_value_", "_member_map_", "_exit", "_getframe"}


#: the compiled extensions setup.py declares (``canrls._can``, ...): private to the package,
#: each imported by the layer whose loops it runs
C_EXTENSIONS = set(re.findall(r"""Extension\(\s*(?:name\s*=\s*)?["']canrls\.(\w+)["']""",
                              (SRC.parent / "setup.py").read_text()))


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, ast.Module]:
    return {module_name(p): ast.parse(p.read_text(), str(p)) for p in sorted(PKG.rglob("*.py"))}


def layer_of(mod: str) -> str:
    """A module's layer: its top-level folder (``canrls.can.decoder``: ``can``)."""
    if mod in ROOT_MODULES:
        return ROOT_MODULES[mod]
    return mod.split(".")[1]


def imports(tree: ast.Module, mod: str) -> Iterator[tuple[str, int]]:
    """Every imported module name (absolute) with its line."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = mod.split(".")[: len(mod.split(".")) - node.level + (
                    1 if (PKG / Path(*mod.split(".")[1:]) / "__init__.py").exists() else 0)]
                base = ".".join([*pkg, base] if base else pkg)
            yield base, node.lineno
            for a in node.names:
                yield f"{base}.{a.name}", node.lineno


def canrls_imports(tree: ast.Module, mod: str, known: set[str]) -> set[tuple[str, int]]:
    """The canrls modules ``mod`` imports (``from canrls.x import y``: ``canrls.x.y`` if that
    is a module, else ``canrls.x``)."""
    out = set()
    for name, line in imports(tree, mod):
        if name == "canrls" or name.startswith("canrls."):
            while name not in known and "." in name:
                name = name.rsplit(".", 1)[0]
            if name != mod:
                out.add((name, line))
    return out


@pytest.fixture(scope="module")
def tree() -> dict[str, ast.Module]:
    return modules()


def test_every_module_is_in_a_layers_folder(tree: dict[str, ast.Module]) -> None:
    loose = [mod for mod in tree if mod not in ROOT_MODULES and layer_of(mod) not in ALLOWED]
    assert not loose, ("modules outside the layers' folders (a module's layer is its "
                       "top-level folder under src/canrls):\n" + "\n".join(sorted(loose)))


def test_imports_go_one_way(tree: dict[str, ast.Module]) -> None:
    known = set(tree)
    bad = []
    for mod, t in tree.items():
        mine = layer_of(mod)
        for dep, line in canrls_imports(t, mod, known):
            if dep == "canrls" and mine != "cli":
                continue  # the package root (__version__) belongs to every layer
            theirs = layer_of(dep)
            if theirs != mine and theirs not in ALLOWED[mine]:
                bad.append(f"{mod}:{line} ({mine}) imports {dep} ({theirs})")
    assert not bad, "imports against the layers:\n" + "\n".join(sorted(bad))


def test_nothing_imports_the_cli(tree: dict[str, ast.Module]) -> None:
    known = set(tree)
    bad = [f"{mod}:{line} imports {dep}" for mod, t in tree.items()
           if layer_of(mod) != "cli" for dep, line in canrls_imports(t, mod, known)
           if layer_of(dep) == "cli"]
    assert not bad, bad


def test_rooms_beside_each_other_do_not_import_each_other(tree: dict[str, ast.Module]) -> None:
    known = set(tree)
    bad = [f"{mod}:{line} ({layer_of(mod)}) imports {dep} ({layer_of(dep)})"
           for mod, t in tree.items() if layer_of(mod) in BESIDE
           for dep, line in canrls_imports(t, mod, known)
           if layer_of(dep) in BESIDE and layer_of(dep) != layer_of(mod)]
    assert not bad, bad


def test_only_the_cli_sees_argparse(tree: dict[str, ast.Module]) -> None:
    bad = [f"{mod}:{line}" for mod, t in tree.items() if layer_of(mod) != "cli"
           for name, line in imports(t, mod) if name.split(".")[0] == "argparse"]
    assert not bad, "argparse below the command line: " + ", ".join(bad)


def test_pure_layers_import_no_io(tree: dict[str, ast.Module]) -> None:
    bad = []
    for mod, t in tree.items():
        if layer_of(mod) not in ("core", "estimation"):
            continue
        for name, line in imports(t, mod):
            if name.split(".")[0] in IO_PACKAGES:
                bad.append(f"{mod}:{line} imports {name}")
    assert not bad, bad


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def import_graph(tree: dict[str, ast.Module]) -> dict[str, set[str]]:
    """Module -> the canrls modules it imports, also for annotations only (``if
    TYPE_CHECKING:``) and inside functions. A module's import of a package it is in
    (``from canrls.estimation.fixed import layout`` in ``fixed.plan``) is left out: Python
    imports a module's packages before the module anyway, and a package's ``__init__``
    importing its own modules is how packages work."""
    known = set(tree)
    return {mod: {d for d, _ in canrls_imports(t, mod, known)
                  if d != "canrls" and not mod.startswith(d + ".")}
            for mod, t in tree.items()}


def test_no_import_circles(tree: dict[str, ast.Module]) -> None:
    cycle = find_cycle(import_graph(tree))
    assert cycle is None, "import circle: " + " -> ".join(cycle or [])


def re_exports(t: ast.Module, mod: str, known: set[str]) -> list[str]:
    """Names a module lists in ``__all__`` but imports from another canrls module."""
    imported = {(a.asname or a.name) for node in t.body if isinstance(node, ast.ImportFrom)
                and (node.module or "").startswith("canrls.") and node.module in known
                for a in node.names}
    listed: list[str] = []
    for node in t.body:
        if isinstance(node, ast.Assign) and any(isinstance(x, ast.Name) and x.id == "__all__"
                                                for x in node.targets):
            listed = list(ast.literal_eval(node.value))
    return [n for n in listed if n in imported]


def is_package(mod: str) -> bool:
    return (PKG / Path(*mod.split(".")[1:]) / "__init__.py").exists()


def test_only_packages_re_export(tree: dict[str, ast.Module]) -> None:
    known = set(tree)
    bad = [f"{mod}: {', '.join(names)}" for mod, t in tree.items() if not is_package(mod)
           for names in [re_exports(t, mod, known)] if names]
    assert not bad, ("modules that re-export their siblings' names (import them from the "
                     "module that defines them; only a package's __init__ re-exports):\n"
                     + "\n".join(sorted(bad)))


def private_names(t: ast.Module) -> set[str]:
    """Underscore names a module defines: functions, classes, methods, attributes."""
    out = set()
    for node in ast.walk(t):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            out.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            out.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            out.add(node.id)
        elif isinstance(node, ast.arg):
            out.add(node.arg)
    return {n for n in out if n.startswith("_") and not n.startswith("__")}


def private_uses(t: ast.Module) -> Iterator[tuple[str, int, bool]]:
    """``x._name`` with ``x`` not ``self``/``cls`` (and whether ``x`` is a plain name, such
    as another instance of the same class, rather than an attribute such as
    ``self.builder``), and ``from m import _name``."""
    for node in ast.walk(t):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__")
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
            yield node.attr, node.lineno, isinstance(node.value, ast.Name)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("canrls"):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    yield "import " + a.name, node.lineno, True


def test_no_module_uses_another_modules_private_names(tree: dict[str, ast.Module]) -> None:
    defined = {mod: private_names(t) for mod, t in tree.items()}
    bad = []
    for mod, t in tree.items():
        own = defined[mod]
        elsewhere = set().union(*(v for k, v in defined.items() if k != mod))
        for name, line, plain in private_uses(t):
            if name in STD_PRIVATE:
                continue
            if name.startswith("import ") and name[len("import "):] in C_EXTENSIONS:
                continue
            if name.startswith("import "):
                bad.append(f"{mod}:{line}: {name}")
            elif name not in own:
                bad.append(f"{mod}:{line}: .{name} is not defined in {mod}")
            elif not plain and name in elsewhere:
                # self.builder._regressors: a name this module defines too, reached
                # through another object that another module defines it on
                bad.append(f"{mod}:{line}: .{name} of an attribute, also defined elsewhere")
    assert not bad, "private names used across modules:\n" + "\n".join(sorted(bad))


#: the longest function and module in src/ [lines] (issue 23)
MAX_FUNCTION_LINES = 150
MAX_MODULE_LINES = 1000
#: a module docstring says what the module is for; the rules, measurements and histories
#: are in docs/ (errors.py's tree of errors and units.py's doctests are the longest)
MAX_MODULE_DOCSTRING_LINES = 35


def long_functions(t: ast.Module, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int, int]]:
    """``(name, line, length)`` of every function or method longer than ``limit`` lines."""
    return [(node.name, node.lineno, (node.end_lineno or node.lineno) - node.lineno + 1)
            for node in ast.walk(t) if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            and (node.end_lineno or node.lineno) - node.lineno + 1 > limit]


def test_no_function_over_150_lines(tree: dict[str, ast.Module]) -> None:
    bad = [f"{mod}:{line} {name}: {n} lines" for mod, t in tree.items()
           for name, line, n in long_functions(t)]
    assert not bad, (f"functions over {MAX_FUNCTION_LINES} lines (split them into steps):\n"
                     + "\n".join(sorted(bad)))


def test_no_module_over_1000_lines() -> None:
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        n = len(path.read_text().splitlines())
        if n > MAX_MODULE_LINES:
            bad.append(f"{path.relative_to(SRC)}: {n} lines")
    assert not bad, f"modules over {MAX_MODULE_LINES} lines:\n" + "\n".join(bad)


def docstring_lines(t: ast.Module) -> int:
    doc = ast.get_docstring(t, clean=False)
    return len(doc.splitlines()) if doc else 0


def test_module_docstrings_are_short(tree: dict[str, ast.Module]) -> None:
    bad = [f"{mod}: {docstring_lines(t)} lines" for mod, t in tree.items()
           if docstring_lines(t) > MAX_MODULE_DOCSTRING_LINES]
    assert not bad, (f"module docstrings over {MAX_MODULE_DOCSTRING_LINES} lines (say what "
                     f"the module is for; the rest belongs in docs/):\n" + "\n".join(bad))


#: a layer's package docstring says what the layer does, in more than a label
MIN_LAYER_DOCSTRING_CHARS = 200


def test_every_layers_package_says_what_the_layer_does(tree: dict[str, ast.Module]) -> None:
    bad = [f"{mod}: {ast.get_docstring(t)!r}" for mod, t in tree.items()
           if mod.count(".") == 1 and is_package(mod)
           and len(ast.get_docstring(t) or "") < MIN_LAYER_DOCSTRING_CHARS]
    assert not bad, "layers whose package docstring does not say what they do:\n" + \
        "\n".join(sorted(bad))


# -- the checks themselves fail where they should ------------------------------------------
def test_the_checks_catch_a_wrong_import_a_circle_and_a_private_call() -> None:
    a = ast.parse("from canrls.cli.main import main\nimport canrls.estimation.model\n")
    deps = {d for d, _ in canrls_imports(a, "canrls.can.protocol",
                                         {"canrls.cli.main", "canrls.estimation.model"})}
    assert layer_of("canrls.can.protocol") == "can"
    assert {layer_of(d) for d in deps} == {"cli", "estimation"}
    assert not ({layer_of(d) for d in deps} & ALLOWED["can"])
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    typed = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                      "    from canrls.can.protocol import Protocol\n")
    assert canrls_imports(typed, "canrls.can.decoder", {"canrls.can.protocol"}) == {
        ("canrls.can.protocol", 3)}
    shim = ast.parse("from canrls.can.decoder import Decoder\n__all__ = ['Decoder', 'x']\n")
    assert re_exports(shim, "canrls.can.protocol", {"canrls.can.decoder"}) == ["Decoder"]
    assert layer_of("canrls.config") == "config" and "config" not in ALLOWED
    assert layer_of("canrls.processor.pairing") == "processor"
    assert layer_of("canrls.__main__") == "cli" and layer_of("canrls") == "core"
    t = ast.parse("def f(builder):\n    return builder._regressors(1)\n"
                  "from canrls.estimation.model import _exponent\n")
    uses = {name: plain for name, _, plain in private_uses(t)}
    assert "_regressors" in uses and "import _exponent" in uses
    t2 = ast.parse("class E:\n    def _regressors(self):\n"
                   "        return self.builder._regressors()\n")
    assert {name: plain for name, _, plain in private_uses(t2)} == {"_regressors": False}
    assert "_regressors" not in private_names(t)
    assert "_x" in private_names(ast.parse("class A:\n    def _x(self):\n        pass\n"))
    assert "live" not in ALLOWED["diagnosis"] and "diagnosis" not in ALLOWED["fleet"]
    long = ast.parse("class A:\n    def f(self):\n" + "        x = 1\n" * 150)
    assert long_functions(long) == [("f", 2, 151)]
    assert long_functions(ast.parse("def g():\n" + "    x = 1\n" * 149)) == []
    assert docstring_lines(ast.parse('"""One.\n\nTwo."""\nx = 1\n')) == 3
    assert docstring_lines(ast.parse("x = 1\n")) == 0
    io = ast.parse("import cantools\n")
    assert [n for n, _ in imports(io, "canrls.estimation.rls")] == ["cantools"]


# -- docs/architecture.md is drawn from the tree --------------------------------------------
#: what the table lists of a folder: its Python modules (by name) and its C
SOURCE_SUFFIXES = {".py", ".c", ".h", ".ld"}


def tree_folders(pkg: Path = PKG) -> dict[str, set[str]]:
    """Each folder under ``pkg`` (``"estimation/fixed/"``) -> its modules (``"svf"``) and C
    files (``"can.c"``), ``__init__`` aside; the package's own top level left out."""
    out: dict[str, set[str]] = {}
    for f in sorted(pkg.rglob("*")):
        if (f.suffix not in SOURCE_SUFFIXES or f.name == "__init__.py"
                or "__pycache__" in f.parts or f.parent == pkg):
            continue
        folder = f.parent.relative_to(pkg).as_posix() + "/"
        out.setdefault(folder, set()).add(f.stem if f.suffix == ".py" else f.name)
    return out


def documented_folders(text: str) -> dict[str, set[str]]:
    """The table of docs/architecture.md's "The tree, in layers": folder -> names."""
    section = text.split("## The tree, in layers", 1)[1].split("\n## ", 1)[0]
    out: dict[str, set[str]] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and re.fullmatch(r"`[\w/]+/`", cells[0]):
            out[cells[0].strip("`")] = set(re.findall(r"`([^`]+)`", cells[2]))
    return out


def test_architecture_md_is_drawn_from_the_tree() -> None:
    have, told = tree_folders(), documented_folders(ARCHITECTURE.read_text())
    bad = [f"{folder}: in the tree {sorted(have.get(folder, ()))}, in the docs "
           f"{sorted(told.get(folder, ()))}" for folder in sorted(set(have) | set(told))
           if have.get(folder) != told.get(folder)]
    assert not bad, ("docs/architecture.md's table of the tree differs from src/canrls:\n"
                     + "\n".join(bad))


def test_the_tree_check_sees_a_missing_module(tmp_path: Path) -> None:
    (tmp_path / "can").mkdir()
    (tmp_path / "can" / "__init__.py").write_text("")
    (tmp_path / "can" / "logs.py").write_text("")
    (tmp_path / "can" / "new.py").write_text("")
    (tmp_path / "loose.py").write_text("")
    assert tree_folders(tmp_path) == {"can/": {"logs", "new"}}
    doc = ("## The tree, in layers\n\n| folder | what | modules |\n|---|---|---|\n"
           "| `can/` | the bus | `logs` |\n\n## Next\n| `sim/` | x | `bus` |\n")
    assert documented_folders(doc) == {"can/": {"logs"}}


# -- names: a file name says which module it is ---------------------------------------------
def repeated_file_names(pkg: Path = PKG) -> dict[str, list[str]]:
    """File names (``results.py``) that more than one module of ``pkg`` has, ``__init__``
    aside, each with its modules' paths: a name of ``cli/`` (a subcommand's) counts too, so
    ``cli/monitor.py`` and the module it drives cannot both be ``monitor.py``."""
    seen: dict[str, list[str]] = {}
    for f in sorted(pkg.rglob("*.py")):
        if f.name != "__init__.py" and "__pycache__" not in f.parts:
            seen.setdefault(f.name, []).append(f.relative_to(pkg).as_posix())
    return {name: paths for name, paths in seen.items() if len(paths) > 1}


def test_no_two_modules_share_a_file_name() -> None:
    bad = repeated_file_names()
    assert not bad, ("file names repeated across folders (name each module for what it "
                     "is):\n" + "\n".join(f"{n}: {', '.join(p)}" for n, p in sorted(bad.items())))


def test_the_name_check_sees_a_repeated_name(tmp_path: Path) -> None:
    for rel in ("live/monitor.py", "cli/monitor.py", "live/__init__.py", "cli/__init__.py",
                "sim/interface.py"):
        (tmp_path / rel).parent.mkdir(exist_ok=True)
        (tmp_path / rel).write_text("")
    assert repeated_file_names(tmp_path) == {"monitor.py": ["cli/monitor.py", "live/monitor.py"]}

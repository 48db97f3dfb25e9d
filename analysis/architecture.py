"""The shape of a jsve checkout: packages, root API, import cycles, shadowed modules, layering, start-up cost.

    python analysis/architecture.py                     # this checkout
    python analysis/architecture.py --root /work/baseline

Reads the source with `ast` (nothing of jsve is imported into this process) and measures start-up in
subprocesses with PYTHONPATH and the working directory set to `--root`, so any checkout can be measured,
the old flat layout included. Bytecode goes to a cache under the temporary directory, never into the
checkout. The import-graph code here is also what tests/test_layers.py enforces (it imports this file by
path): one home for the layer map and for reading imports.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

PACKAGE = "jsve"

ANYTHING = None
"""Marks a layer that may import any other (the entry points)."""

LAYERS: dict[str, frozenset[str] | None] = {
    # Lowest first. The value lists the layers a layer may import, besides itself and `_version`.
    "_version": frozenset(),
    # JAX's persistent compilation cache, switched on by the commands that compute (cli, _demo).
    "_jax_cache": frozenset(),
    # Giving memory back between the stages of a long job (JAX's executables, the heap): fitting's stages
    # and evaluation's pass over a study (the executables of the frame lengths it has left behind).
    "_memory": frozenset(),
    "core": frozenset(),
    "io": frozenset({"core"}),
    "evaluation": frozenset({"_memory", "core", "io"}),
    "image": frozenset({"core", "io"}),
    # Table I (masks/_table_one.py) scores masked against original runs with evaluation's pose scoring and
    # per-run table: one home for alignment and APE tables, so masks sits above evaluation.
    "masks": frozenset({"core", "io", "evaluation"}),
    # The simulator writes format-v1 logs through io, decides frames with core's state machine, and masks
    # the driving sequences with Algorithm 1 (sim/_driving.py); it needs nothing from image.
    "sim": frozenset({"core", "io", "masks"}),
    "fitting": frozenset({"_memory", "core", "io", "evaluation"}),
    "report": frozenset({"core", "io", "evaluation", "fitting", "tuning"}),
    "_demo": ANYTHING,
    "cli": ANYTHING,
    # The compiled front-end's Python side: the build (standard library only) and the vocabulary, which
    # extracts ORB with image's settings and writes through io.
    "frontend": frozenset({"core", "io", "image"}),
    # Rendered EuRoC-format sequences for the real front-end: trajectories and IMU synthesis from sim,
    # the camera model from image.
    "render": frozenset({"core", "io", "image", "sim"}),
    # Rules tuned in the loop: runs of the front-end (or the simulator, to rehearse), the replay's
    # proposals (fitting, evaluation) and paired tests over the runs.
    "tuning": frozenset({"core", "io", "evaluation", "fitting", "frontend", "sim"}),
    # The root package itself (jsve/__init__.py) re-exports everything.
    "": ANYTHING,
}
"""Layer (the component after `jsve.`) -> the layers it may import. tests/test_layers.py enforces it."""

EVERYONE_MAY_IMPORT = frozenset({"_version"})
"""Leaf modules of constants any layer may import."""

CORE_THIRD_PARTY = frozenset({"jax", "jaxtyping", "equinox", "numpy"})
"""The only packages beyond the standard library that jsve.core may import: arrays in, arrays out."""

HEAVY = ("jax", "pandas", "matplotlib", "cv2")
"""Packages whose presence in sys.modules after `import jsve` is reported."""


@dataclass(frozen=True)
class Import:
    """One import statement's target, as the importing module sees it.

    Attributes:
        importer: dotted name of the importing module (`jsve.io._logs`; a package is its own name).
        path: file of the importer.
        lineno: line of the statement.
        target: what the statement loads: the most specific jsve module it names
            (`from jsve.io import _schema` -> `jsve.io._schema`, `from jsve.io import RunLog` -> `jsve.io`),
            or the dotted external name.
        text: the statement as written (first line).
        module_level: executed when the importer is imported (not inside a function, not under TYPE_CHECKING).
    """

    importer: str
    path: Path
    lineno: int
    target: str
    text: str
    module_level: bool

    @property
    def internal(self) -> bool:
        return self.target == PACKAGE or self.target.startswith(PACKAGE + ".")

    @property
    def top_package(self) -> str:
        return self.target.split(".")[0]

    def where(self, root: Path) -> str:
        """`jsve/io/_logs.py:12: from jsve.core import x` for messages."""
        try:
            shown = self.path.relative_to(root)
        except ValueError:
            shown = self.path
        return f"{shown}:{self.lineno}: {self.text}"


def find_modules(root: Path) -> dict[str, Path]:
    """Every Python module of the package under `root`, by dotted name (`jsve.io._logs`, `jsve.io`)."""
    base = Path(root) / PACKAGE
    if not (base / "__init__.py").is_file():
        raise FileNotFoundError(f"{base}/__init__.py not found: --root must be a checkout of {PACKAGE}")
    modules: dict[str, Path] = {}
    for path in sorted(base.rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if "__pycache__" in parts:
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _is_package(name: str, modules: Mapping[str, Path]) -> bool:
    return modules[name].name == "__init__.py"


def _resolve_relative(importer: str, level: int, module: str | None, modules: Mapping[str, Path]) -> str:
    package = importer if _is_package(importer, modules) else importer.rpartition(".")[0]
    parts = package.split(".")
    if level - 1 > len(parts) - 1:
        raise ImportError(f"{modules[importer]}: relative import beyond the top-level package")
    base = ".".join(parts[: len(parts) - (level - 1)])
    return f"{base}.{module}" if module else base


def _from_base(importer: str, node: ast.ImportFrom, modules: Mapping[str, Path]) -> str:
    """The absolute module a `from ... import` statement in `importer` reads from."""
    if node.level:
        return _resolve_relative(importer, node.level, node.module, modules)
    return node.module or ""


def _known_module(name: str, modules: Mapping[str, Path]) -> str:
    """The longest prefix of `name` that is a module of the package (`name` itself when external).

    A jsve name with no module behind it keeps its layer: `jsve.plots.x` -> `jsve.plots`.
    """
    if not (name == PACKAGE or name.startswith(PACKAGE + ".")):
        return name
    parts = name.split(".")
    while len(parts) > 2 and ".".join(parts) not in modules:
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _walk_imports(tree: ast.AST) -> Iterable[tuple[ast.Import | ast.ImportFrom, bool]]:
    """(import node, executed at import time) for every import anywhere in the tree."""

    def visit(node: ast.AST, module_level: bool) -> Iterable[tuple[ast.Import | ast.ImportFrom, bool]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import | ast.ImportFrom):
                yield child, module_level
            elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                yield from visit(child, False)
            elif isinstance(child, ast.If) and _is_type_checking(child.test):
                for stmt in child.body:
                    yield from visit(ast.Module(body=[stmt], type_ignores=[]), False)
                for stmt in child.orelse:
                    yield from visit(ast.Module(body=[stmt], type_ignores=[]), module_level)
            else:
                yield from visit(child, module_level)

    yield from visit(tree, True)


def imports_of(name: str, modules: Mapping[str, Path]) -> list[Import]:
    """Every import in module `name`, function-level ones included, with jsve targets resolved to modules."""
    path = modules[name]
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    found = []
    for node, module_level in _walk_imports(ast.parse(source, filename=str(path))):
        text = lines[node.lineno - 1].strip()
        if isinstance(node, ast.Import):
            targets = [_known_module(alias.name, modules) for alias in node.names]
        else:
            if node.module == "__future__":
                continue
            base = _from_base(name, node, modules)
            targets = []
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                targets.append(submodule if submodule in modules else _known_module(base, modules))
        for target in dict.fromkeys(targets):
            found.append(Import(name, path, node.lineno, target, text, module_level))
    return found


def import_graph(root: Path) -> tuple[dict[str, Path], list[Import]]:
    """All modules under `root`/jsve and all their imports."""
    modules = find_modules(root)
    return modules, [imp for name in modules for imp in imports_of(name, modules)]


def is_layered(root: Path) -> bool:
    """True for the layered tree (jsve/core is a package), False for the old flat one."""
    return (Path(root) / PACKAGE / "core" / "__init__.py").is_file()


def layer_of(module: str) -> str:
    """The layer of a jsve module: the component after `jsve.` (`jsve.io._logs` -> `io`; `jsve` -> "")."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def unknown_layers(modules: Iterable[str]) -> list[str]:
    """Modules whose layer the map does not place (a new subpackage must be given its place)."""
    return sorted(m for m in modules if layer_of(m) not in LAYERS)


def layering_violations(imports: Iterable[Import]) -> list[Import]:
    """Imports, anywhere in a module, of a layer the importer's layer may not import."""
    bad = []
    for imp in imports:
        if not imp.internal:
            continue
        source, target = layer_of(imp.importer), layer_of(imp.target)
        allowed = LAYERS.get(source, frozenset())
        if allowed is None or target == source or target in EVERYONE_MAY_IMPORT or target in allowed:
            continue
        bad.append(imp)
    return bad


def third_party_in(imports: Iterable[Import], layer: str, allowed: frozenset[str]) -> list[Import]:
    """Imports in `layer` of packages that are neither the standard library, jsve, nor in `allowed`."""
    return [
        imp
        for imp in imports
        if layer_of(imp.importer) == layer
        and not imp.internal
        and imp.top_package not in sys.stdlib_module_names
        and imp.top_package not in allowed
    ]


def import_cycles(imports: Iterable[Import], module_level_only: bool = True) -> list[list[str]]:
    """Cycles among jsve modules through module-level imports: one cycle per strongly connected component.

    Arguments:
        imports: the imports of the package (`import_graph`).
        module_level_only: False counts imports inside functions and under TYPE_CHECKING too: the cycles
            that deferring an import only hides.

    Returns:
        Each cycle as the list of modules along it, the first repeated at the end (`[a, b, a]`).
    """
    graph: dict[str, set[str]] = {}
    for imp in imports:
        if imp.internal and (imp.module_level or not module_level_only):
            graph.setdefault(imp.importer, set()).add(imp.target)
            graph.setdefault(imp.target, set())
    # Tarjan (1972), iteratively: strongly connected components.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in graph[node]:
                    components.append(sorted(component))
    return [_cycle_through(component, graph) for component in sorted(components)]


def _cycle_through(component: list[str], graph: Mapping[str, set[str]]) -> list[str]:
    """A shortest cycle from the component's first member back to it (breadth-first inside the component)."""
    start, members = component[0], set(component)
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(graph[node] & members):
                if child == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [*reversed(path), start]
                if child not in previous:
                    previous[child] = node
                    following.append(child)
        frontier = following
    raise AssertionError(f"{component} is not strongly connected")


def _stub_or_init(package_path: Path) -> Path:
    stub = package_path.with_suffix(".pyi")
    return stub if stub.is_file() else package_path


@dataclass(frozen=True)
class Binding:
    """A name a package's `__init__` (or its `.pyi` stub, which lazy_loader reads) binds at top level."""

    package: str
    name: str
    path: Path
    lineno: int
    text: str
    module: str | None
    """The jsve module the name is bound to, when it is bound to a module (`from . import core as core`)."""


def package_bindings(package: str, modules: Mapping[str, Path]) -> list[Binding]:
    """Top-level names bound by a package's `__init__.pyi` if it has one, else its `__init__.py`."""
    path = _stub_or_init(modules[package])
    lines = path.read_text(encoding="utf-8").splitlines()
    tree = ast.parse("\n".join(lines), filename=str(path))
    found = []
    for node in tree.body:
        text = lines[node.lineno - 1].strip()
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            base = _from_base(package, node, modules)
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                found.append(
                    Binding(
                        package,
                        alias.asname or alias.name,
                        path,
                        node.lineno,
                        text,
                        submodule if submodule in modules else None,
                    )
                )
        elif isinstance(node, ast.Import):
            for alias in node.names:
                bound = alias.asname or alias.name.split(".")[0]
                target = alias.name if alias.asname else alias.name.split(".")[0]
                found.append(
                    Binding(package, bound, path, node.lineno, text, target if target in modules else None)
                )
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            found.append(Binding(package, node.name, path, node.lineno, text, None))
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                for name in ast.walk(target):
                    if isinstance(name, ast.Name):
                        found.append(Binding(package, name.id, path, node.lineno, text, None))
    return found


def shadowed_modules(modules: Mapping[str, Path]) -> list[Binding]:
    """Names a package binds that equal one of its submodules' names but are not that module.

    After `from .fit import fit`, `jsve.fit` is the function and the module is out of reach as an
    attribute; `import jsve.fit` then gives one object and `jsve.fit` another.
    """
    shadows = []
    for package in modules:
        if not _is_package(package, modules):
            continue
        for binding in package_bindings(package, modules):
            submodule = f"{package}.{binding.name}"
            if submodule in modules and binding.module != submodule:
                shadows.append(binding)
    return shadows


def root_api(root: Path) -> list[str]:
    """The names the root package exports: public names bound in jsve/__init__.pyi (or __init__.py)."""
    modules = find_modules(root)
    names = [b.name for b in package_bindings(PACKAGE, modules)]
    return sorted({n for n in names if not n.startswith("_") or n == "__version__"})


def subcommand_modules(modules: Mapping[str, Path]) -> set[str]:
    """`jsve.cli.<name>` for each subcommand listed in `jsve.cli.SUBCOMMANDS` (read with ast)."""
    cli = f"{PACKAGE}.cli"
    if cli not in modules:
        return set()
    for node in ast.parse(modules[cli].read_text(encoding="utf-8")).body:
        if isinstance(node, ast.AnnAssign):
            target, value = node.target, node.value
        elif isinstance(node, ast.Assign) and len(node.targets) == 1:
            target, value = node.targets[0], node.value
        else:
            continue
        if isinstance(target, ast.Name) and target.id == "SUBCOMMANDS" and value is not None:
            return {f"{cli}.{name.replace('-', '_')}" for name in ast.literal_eval(value)}
    return set()


def public_module_names(modules: Mapping[str, Path]) -> list[str]:
    """Non-package modules with a public name, other than `__main__` and the CLI's subcommand modules."""
    subcommands = subcommand_modules(modules)
    return sorted(
        name
        for name in modules
        if not _is_package(name, modules)
        and not name.rpartition(".")[2].startswith("_")
        and name not in subcommands
    )


SCRIPT_FOLDERS = ("analysis", "sweeps")
"""Folders of scripts that use jsve through its public names only (the packages' `__init__` exports)."""


@dataclass(frozen=True)
class PrivateUse:
    """A script's import or attribute access that names a private part of jsve.

    Attributes:
        path: the script. lineno: the line.
        name: the dotted name up to and including its first private component (`jsve.io._atomic`).
        text: the line as written.
    """

    path: Path
    lineno: int
    name: str
    text: str

    def where(self, root: Path) -> str:
        """`analysis/x.py:12: from jsve.io._atomic import write_text` for messages."""
        try:
            shown = self.path.relative_to(root)
        except ValueError:
            shown = self.path
        return f"{shown}:{self.lineno}: {self.text}"


def _first_private(dotted: str) -> str | None:
    """`jsve.io._atomic.write_text` -> `jsve.io._atomic`; None when every component is public."""
    parts = dotted.split(".")
    if parts[0] != PACKAGE:
        return None
    for i, part in enumerate(parts):
        if part.startswith("_") and not (part.startswith("__") and part.endswith("__")):
            return ".".join(parts[: i + 1])
    return None


def _dotted(node: ast.expr) -> str | None:
    """`a.b.c` for a chain of attributes on a name, else None."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([node.id, *reversed(parts)])


def private_uses(path: Path) -> list[PrivateUse]:
    """Where a script imports or names private jsve modules or names, function-level imports included.

    Counted: `import jsve.io._atomic`, `from jsve.io._atomic import x`, `from jsve.io import _schema`,
    and attribute chains on the package (`jsve.core._batch.pad_runs`, after `import jsve`). Strings and
    comments are not read.
    """
    source = Path(path).read_text(encoding="utf-8")
    lines = source.splitlines()
    tree = ast.parse(source, filename=str(path))
    found: dict[tuple[int, str], PrivateUse] = {}

    def add(node: ast.AST, name: str | None) -> None:
        if name is not None:
            found.setdefault(
                (node.lineno, name), PrivateUse(Path(path), node.lineno, name, lines[node.lineno - 1].strip())
            )

    for node, _ in _walk_imports(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(node, _first_private(alias.name))
        elif node.level == 0 and node.module:
            private = _first_private(node.module)
            add(node, private)
            if private is None:
                for alias in node.names:
                    add(node, _first_private(f"{node.module}.{alias.name}"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            dotted = _dotted(node)
            if dotted is not None and _first_private(dotted) == dotted:
                add(node, dotted)
    return sorted(found.values(), key=lambda u: (u.lineno, u.name))


def script_private_uses(root: Path, folders: Iterable[str] = SCRIPT_FOLDERS) -> list[PrivateUse]:
    """`private_uses` of every Python file under the script folders of the checkout at `root`."""
    return [
        use
        for folder in folders
        for path in sorted((Path(root) / folder).rglob("*.py"))
        if "__pycache__" not in path.parts
        for use in private_uses(path)
    ]


def _subprocess_env(root: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(root).resolve())
    # Bytecode beside the sources would write into the measured checkout; keep it in one cache instead.
    env["PYTHONPYCACHEPREFIX"] = str(Path(tempfile.gettempdir()) / "jsve-architecture-pycache")
    return env


def _run_python(root: Path, code: str) -> subprocess.CompletedProcess[str]:
    # cwd=root as well: `python -c` and `-m` put the working directory ahead of PYTHONPATH.
    return subprocess.run(
        [sys.executable, "-c", code],
        cwd=root,
        env=_subprocess_env(root),
        capture_output=True,
        text=True,
        timeout=600,
    )


def unresolved_root_names(root: Path) -> dict[str, str]:
    """Names of the root API that `getattr(jsve, name)` fails on, with the error, imported in a subprocess."""
    code = (
        "import json, jsve\n"
        f"names = {root_api(root)!r}\n"
        "bad = {}\n"
        "for n in names:\n"
        "    try:\n"
        "        getattr(jsve, n)\n"
        "    except Exception as e:\n"
        "        bad[n] = f'{type(e).__name__}: {e}'\n"
        "print(json.dumps(bad))\n"
    )
    done = _run_python(root, code)
    if done.returncode != 0:
        return {"import jsve": (done.stderr.strip() or "failed").splitlines()[-1]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def loaded_by_import(root: Path) -> dict[str, bool]:
    """Which of HEAVY are in sys.modules after a bare `import jsve` (in a subprocess)."""
    code = (
        "import json, sys, jsve\n"
        f"assert jsve.__file__.startswith({str(Path(root).resolve())!r}), jsve.__file__\n"
        f"print(json.dumps({{m: m in sys.modules for m in {HEAVY!r}}}))\n"
    )
    done = _run_python(root, code)
    if done.returncode != 0:
        raise RuntimeError(f"import jsve failed under {root}:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def loaded_by_help(root: Path) -> dict[str, bool]:
    """Which of HEAVY are in sys.modules after `jsve --help` has printed (in a subprocess)."""
    code = (
        "import json, runpy, sys\n"
        "sys.argv = ['jsve', '--help']\n"
        "try:\n"
        f"    runpy.run_module('{PACKAGE}.cli', run_name='__main__', alter_sys=True)\n"
        "except SystemExit:\n"
        "    pass\n"
        f"print(json.dumps({{m: m in sys.modules for m in {HEAVY!r}}}))\n"
    )
    done = _run_python(root, code)
    if done.returncode != 0:
        raise RuntimeError(f"jsve --help failed under {root}:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def help_seconds(root: Path, runs: int = 5) -> float:
    """Median wall time of `python -m jsve.cli --help` over `runs` runs, after one warm-up run."""
    command = [sys.executable, "-m", f"{PACKAGE}.cli", "--help"]
    times = []
    for i in range(runs + 1):
        start = time.perf_counter()
        done = subprocess.run(command, cwd=root, env=_subprocess_env(root), capture_output=True, text=True)
        elapsed = time.perf_counter() - start
        if done.returncode != 0:
            raise RuntimeError(f"jsve --help failed under {root}:\n{done.stderr}")
        if i:  # the first run fills the bytecode cache
            times.append(elapsed)
    return statistics.median(times)


def package_sizes(modules: Mapping[str, Path]) -> dict[str, tuple[int, int]]:
    """(package) -> (modules, lines) for the root and each subpackage, counting .py files."""
    sizes: dict[str, tuple[int, int]] = {}
    for name, path in modules.items():
        package = name if _is_package(name, modules) else name.rpartition(".")[0]
        n, lines = sizes.get(package, (0, 0))
        sizes[package] = (n + 1, lines + len(path.read_text(encoding="utf-8").splitlines()))
    return dict(sorted(sizes.items()))


def function_lengths(modules: Mapping[str, Path]) -> list[tuple[int, str]]:
    """(lines, `module.function`) of every function and method, longest first; a function's lines run
    from its `def` (decorators excluded) to its last statement, nested functions counted in it."""
    found = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                end = node.end_lineno if node.end_lineno is not None else node.lineno
                found.append((end - node.lineno + 1, f"{name}.{node.name}"))
    return sorted(found, key=lambda item: (-item[0], item[1]))


def exported_names(root: Path, package: str) -> list[str]:
    """The names a subpackage's `__init__.py` re-exports (`from x import a as a`, or its `__all__`)."""
    init = Path(root) / package.replace(".", "/") / "__init__.py"
    tree = ast.parse(init.read_text(encoding="utf-8"))
    names = [a.asname or a.name for n in tree.body if isinstance(n, ast.ImportFrom) for a in n.names]
    return sorted(n for n in names if not n.startswith("_"))


def shape(root: Path, top: int = 5, long_module: int = 700) -> str:
    """Markdown: jsve.fitting's exported names, the longest functions, the modules over `long_module`
    lines and the largest modules of the checkout at `root`."""
    modules = find_modules(Path(root).resolve())
    lines = sorted(
        ((len(p.read_text(encoding="utf-8").splitlines()), n) for n, p in modules.items()), reverse=True
    )
    longest = function_lengths(modules)
    over = [(n, m) for n, m in lines if n > long_module]
    rows = [
        ("`jsve.fitting` exported names", str(len(exported_names(root, "jsve.fitting")))),
        (f"longest functions (top {top})", "; ".join(f"`{f}` {n}" for n, f in longest[:top])),
        ("functions over 100 lines", str(sum(n > 100 for n, _ in longest))),
        (f"modules over {long_module} lines", f"{len(over)}: " + "; ".join(f"`{m}` {n}" for n, m in over)),
        (f"largest modules (top {top})", "; ".join(f"`{m}` {n}" for n, m in lines[:top])),
    ]
    return _table(rows, ("measure", "value"))


def _table(rows: list[tuple[str, ...]], header: tuple[str, ...]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(out)


def _listing(items: list[str]) -> str:
    return f"{len(items)}" + (": " + "; ".join(f"`{i}`" for i in items) if items else "")


def _yes_no(loaded: Mapping[str, bool]) -> str:
    return ", ".join(f"{m} {'yes' if v else 'no'}" for m, v in loaded.items())


def report(root: Path, help_runs: int = 5) -> str:
    """The Markdown tables for the checkout at `root`."""
    root = Path(root).resolve()
    modules, imports = import_graph(root)
    sizes = package_sizes(modules)
    packages = [(package, str(n), str(lines)) for package, (n, lines) in sizes.items()]
    packages.append(
        (
            "**total**",
            str(sum(n for n, _ in sizes.values())),
            str(sum(lines for _, lines in sizes.values())),
        )
    )
    if is_layered(root):
        layering = _listing([v.where(root) for v in layering_violations(imports)])
        core_extra = _listing([i.where(root) for i in third_party_in(imports, "core", CORE_THIRD_PARTY)])
    else:
        layering = core_extra = "n/a (flat)"
    summary = [
        ("names re-exported by the root", str(len(root_api(root)))),
        ("root names that fail to resolve", _listing(sorted(unresolved_root_names(root)))),
        ("import cycles (module-level)", _listing([" -> ".join(c) for c in import_cycles(imports)])),
        (
            "import cycles (function-level imports too)",
            _listing([" -> ".join(c) for c in import_cycles(imports, module_level_only=False)]),
        ),
        (
            "modules shadowed by a same-named attribute",
            _listing([f"{b.package}.{b.name}" for b in shadowed_modules(modules)]),
        ),
        ("non-API modules with public names", _listing(public_module_names(modules))),
        ("layering violations", layering),
        ("core imports beyond " + ", ".join(sorted(CORE_THIRD_PARTY)), core_extra),
        (f"`jsve --help` wall time (median of {help_runs})", f"{help_seconds(root, help_runs):.2f} s"),
        ("`import jsve` loads", _yes_no(loaded_by_import(root))),
        ("`jsve --help` loads", _yes_no(loaded_by_help(root))),
    ]
    return "\n".join(
        [
            f"### {root}",
            "",
            _table(packages, ("package", "modules", "lines")),
            "",
            _table(summary, ("measure", "value")),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="The shape of a jsve checkout, as Markdown tables.")
    parser.add_argument(
        "--root",
        type=Path,
        default=Path(__file__).resolve().parents[1],
        help="checkout to measure (the folder holding jsve/); default: this one",
    )
    parser.add_argument("--help-runs", type=int, default=5, help="runs of `jsve --help` to take a median of")
    parser.add_argument(
        "--shape",
        action="store_true",
        help="the code's shape only: exports, longest functions, largest modules",
    )
    args = parser.parse_args(argv)
    print(shape(args.root) if args.shape else report(args.root, args.help_runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())

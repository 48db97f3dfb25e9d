"""The package's shape: layers import only downward, no import cycles, private module names, no shadowing;
scripts (analysis/, sweeps/) use public names.

Read with `ast` from the source (analysis/architecture.py holds the layer map and the import graph; this file
imports it by path), so the checks see function-level imports too and need no import of jsve, except the
last, which resolves every root name in a subprocess. Each checker is also run on a small tree written to
tmp_path with the fault it must catch.
"""

from __future__ import annotations

import importlib.util
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _architecture():
    """analysis/architecture.py, imported by path: analysis/ is a folder of scripts, not a package."""
    name = "analysis_architecture"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "analysis" / "architecture.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up while the class is built
        spec.loader.exec_module(module)
    return sys.modules[name]


arch = _architecture()

KNOWN = {
    # (importer, imported) -> why it is still there. Each entry is a real fault the layering names; the
    # entry goes with its fix, and test_known_faults_are_still_there fails once the import is gone.
}


KNOWN_SCRIPT_USES = {
    # (script, private name) -> why the script still names it: no public export exists yet. The entry goes
    # when the package exports the name; test_known_script_uses_are_still_there fails once it is unused.
}


def _unknown(found, root: Path) -> list[str]:
    return [i.where(root) for i in found if (i.importer, i.target) not in KNOWN]


@pytest.fixture(scope="module")
def graph():
    return arch.import_graph(ROOT)


def test_the_tree_is_layered():
    assert arch.is_layered(ROOT), f"{ROOT}/jsve/core/__init__.py missing: the layered tree is expected"


def test_every_module_has_a_layer(graph):
    modules, _ = graph
    unknown = arch.unknown_layers(modules)
    assert not unknown, (
        f"modules of no layer: {unknown}; give their folder a place in LAYERS in analysis/architecture.py"
    )


def test_no_layer_imports_a_higher_one(graph):
    _, imports = graph
    bad = _unknown(arch.layering_violations(imports), ROOT)
    assert not bad, "imports of a higher layer (anywhere in a module):\n" + "\n".join(bad)


def test_core_imports_only_array_libraries(graph):
    _, imports = graph
    bad = _unknown(arch.third_party_in(imports, "core", arch.CORE_THIRD_PARTY), ROOT)
    assert not bad, (
        f"jsve.core may import only {sorted(arch.CORE_THIRD_PARTY)} beyond the standard library:\n"
        + "\n".join(bad)
    )


def test_known_faults_are_still_there(graph):
    """A listed fault that is fixed must leave KNOWN, so the list never hides a new one."""
    _, imports = graph
    found = {(i.importer, i.target) for i in arch.layering_violations(imports)}
    found |= {(i.importer, i.target) for i in arch.third_party_in(imports, "core", arch.CORE_THIRD_PARTY)}
    gone = sorted(set(KNOWN) - found)
    assert not gone, f"fixed, remove from KNOWN in tests/test_layers.py: {gone}"


def test_scripts_use_public_names():
    """analysis/ and sweeps/ import jsve's public names, not its private modules (STYLE.md, Layout)."""
    uses = [u for u in arch.script_private_uses(ROOT) if (_script(u), u.name) not in KNOWN_SCRIPT_USES]
    assert not uses, "scripts that name private parts of jsve (use the package's export):\n" + "\n".join(
        u.where(ROOT) for u in uses
    )


def test_known_script_uses_are_still_there():
    """A listed private use that is gone must leave KNOWN_SCRIPT_USES, so the list never hides a new one."""
    found = {(_script(u), u.name) for u in arch.script_private_uses(ROOT)}
    gone = sorted(set(KNOWN_SCRIPT_USES) - found)
    assert not gone, f"fixed, remove from KNOWN_SCRIPT_USES in tests/test_layers.py: {gone}"


def _script(use) -> str:
    return use.path.relative_to(ROOT).as_posix()


def test_no_import_cycles(graph):
    _, imports = graph
    cycles = arch.import_cycles(imports)
    assert not cycles, "import cycles through module-level imports:\n" + "\n".join(
        " -> ".join(c) for c in cycles
    )


def test_modules_have_private_names(graph):
    modules, _ = graph
    public = arch.public_module_names(modules)
    assert not public, (
        "modules that are not API need private names (the package re-exports their names): "
        + ", ".join(str(modules[m].relative_to(ROOT)) for m in public)
    )


def test_no_attribute_shadows_a_module(graph):
    modules, _ = graph
    shadows = arch.shadowed_modules(modules)
    assert not shadows, "a package binds the name of one of its modules to something else:\n" + "\n".join(
        f"{b.path.relative_to(ROOT)}:{b.lineno}: {b.text}  (shadows {b.package}.{b.name})" for b in shadows
    )


def test_root_api_resolves():
    names = arch.root_api(ROOT)
    assert len(names) > 50, f"jsve/__init__.pyi lists only {names}"
    bad = arch.unresolved_root_names(ROOT)
    assert not bad, "names of jsve/__init__.pyi that `getattr(jsve, name)` fails on:\n" + "\n".join(
        f"{n}: {e}" for n, e in bad.items()
    )


# The checkers on trees written with the faults they must find.


def _tree(root: Path, files: dict[str, str]) -> Path:
    """A jsve package under `root`: every folder gets an __init__.py unless `files` gives one."""
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    for folder in [root / "jsve", *(root / "jsve").rglob("*")]:
        if folder.is_dir() and not (folder / "__init__.py").exists():
            (folder / "__init__.py").write_text("")
    return root


def test_layering_checker_finds_an_upward_import_inside_a_function(tmp_path):
    root = _tree(
        tmp_path,
        {
            "jsve/core/_a.py": """
                import numpy as np
                from jsve._version import v

                def f():
                    from jsve.fitting._fit import fit
                    return fit
            """,
            "jsve/io/_b.py": "from jsve.core._a import f\nfrom . import _c\n",
            "jsve/io/_c.py": "",
            "jsve/sim/_d.py": "from jsve.image import x\n",
            "jsve/fitting/_fit.py": "from jsve.evaluation import e\n",
            "jsve/_version.py": "v = 1\n",
        },
    )
    _, imports = arch.import_graph(root)
    found = sorted((i.where(root), i.module_level) for i in arch.layering_violations(imports))
    assert found == [
        ("jsve/core/_a.py:6: from jsve.fitting._fit import fit", False),
        ("jsve/sim/_d.py:1: from jsve.image import x", True),
    ]


def test_core_checker_finds_pandas_but_not_numpy(tmp_path):
    root = _tree(
        tmp_path,
        {
            "jsve/core/_a.py": "import jax.numpy as jnp\nimport equinox as eqx\nimport math\n",
            "jsve/core/_b.py": "def f():\n    import pandas as pd\n",
            "jsve/io/_c.py": "import pandas as pd\n",
        },
    )
    _, imports = arch.import_graph(root)
    found = [i.where(root) for i in arch.third_party_in(imports, "core", arch.CORE_THIRD_PARTY)]
    assert found == ["jsve/core/_b.py:2: import pandas as pd"]


def test_cycle_checker_finds_module_level_cycles_only(tmp_path):
    root = _tree(
        tmp_path,
        {
            "jsve/io/_a.py": "from jsve.io import _b\n",
            "jsve/io/_b.py": "from jsve.io._c import x\n",
            "jsve/io/_c.py": "from ._a import y\n",
            # A function-level import back is no cycle at import time.
            "jsve/core/_d.py": "from jsve.core._e import z\n",
            "jsve/core/_e.py": "def g():\n    from jsve.core._d import w\n",
            # Importing the package's own __init__ from inside it is.
            "jsve/sim/__init__.py": "from jsve.sim._f import f\n",
            "jsve/sim/_f.py": "from jsve.sim import g\n",
        },
    )
    _, imports = arch.import_graph(root)
    assert arch.import_cycles(imports) == [
        ["jsve.io._a", "jsve.io._b", "jsve.io._c", "jsve.io._a"],
        ["jsve.sim", "jsve.sim._f", "jsve.sim"],
    ]
    deferred = arch.import_cycles(imports, module_level_only=False)
    assert ["jsve.core._d", "jsve.core._e", "jsve.core._d"] in deferred


def test_private_name_checker(tmp_path):
    root = _tree(
        tmp_path,
        {
            "jsve/io/logs.py": "",
            "jsve/io/_logs.py": "",
            "jsve/io/__main__.py": "",
            "jsve/cli/__init__.py": 'SUBCOMMANDS: tuple[str, ...] = ("ingest", "frontend-include")\n',
            "jsve/cli/ingest.py": "",
            "jsve/cli/frontend_include.py": "",
            "jsve/cli/helpers.py": "",
            "jsve/demo.py": "",
        },
    )
    modules = arch.find_modules(root)
    assert arch.public_module_names(modules) == ["jsve.cli.helpers", "jsve.demo", "jsve.io.logs"]


def test_shadow_checker(tmp_path):
    stub = "from . import core as core\nfrom .fitting._fit import fit as fit\nreport = 1\n"
    root = _tree(
        tmp_path,
        {
            "jsve/__init__.py": "import lazy_loader\n",
            # The stub, not __init__.py, is what a lazy root exports.
            "jsve/__init__.pyi": stub,
            "jsve/core/_sve.py": "",
            "jsve/fitting/__init__.py": "from jsve.fitting import fit as fit\nfrom ._fit import fit",
            "jsve/fitting/fit.py": "",
            "jsve/fitting/_fit.py": "",
            "jsve/report.py": "",
        },
    )
    shadows = arch.shadowed_modules(arch.find_modules(root))
    assert sorted((b.package, b.name, b.lineno) for b in shadows) == [
        ("jsve", "report", 3),
        ("jsve.fitting", "fit", 2),
    ]


def test_script_checker_finds_private_imports_and_attributes(tmp_path):
    script = tmp_path / "analysis" / "s.py"
    script.parent.mkdir()
    script.write_text(
        textwrap.dedent(
            """
            import jsve
            import jsve.io._atomic
            from jsve.core import _levels, pad_runs
            from jsve.sim._trajectory import quat_to_matrix
            from jsve import __version__, core

            def f():
                from jsve.io._atomic import write_text  # a function-level import counts too
                return jsve.core._batch.pad_runs, jsve.core.pad_runs, core.__name__, "jsve.core._sve"
            """
        )
    )
    found = [(u.lineno, u.name) for u in arch.script_private_uses(tmp_path)]
    assert found == [
        (3, "jsve.io._atomic"),
        (4, "jsve.core._levels"),
        (5, "jsve.sim._trajectory"),
        (9, "jsve.io._atomic"),
        (10, "jsve.core._batch"),
    ]


def test_root_api_checker_names_a_missing_name(tmp_path):
    root = _tree(
        tmp_path,
        {
            "jsve/__init__.py": (
                "import lazy_loader as _lazy\n\n"
                "__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)\n"
            ),
            "jsve/__init__.pyi": "from .core import there as there\nfrom .core import gone as gone\n",
            "jsve/core/__init__.py": "there = 1\n",
        },
    )
    assert arch.root_api(root) == ["gone", "there"]
    assert list(arch.unresolved_root_names(root)) == ["gone"]

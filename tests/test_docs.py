"""The documentation site builds (`mkdocs build --strict`: no broken link, missing reference or griffe warning) and its
API reference documents every public name of `piezojax` and `fitting`, each once, as its own entry."""

import importlib.util
import os
import pathlib
import re
import subprocess
import sys
import types
import zlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS_PACKAGES = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python", "mkdocs_jupyter")


def public_names(module: types.ModuleType) -> list[str]:
    """`module.__all__`, or, where it has none, the names it binds without a leading underscore (not submodules)."""
    if hasattr(module, "__all__"):
        return list(module.__all__)
    return [n for n, v in vars(module).items() if not n.startswith("_") and not isinstance(v, types.ModuleType)]


def read_inventory(path: pathlib.Path) -> set[str]:
    """The object names of a Sphinx inventory (version 2, as mkdocstrings writes it): four header lines, then zlib."""
    raw = path.read_bytes()
    header = raw.split(b"\n", 4)
    assert header[0] == b"# Sphinx inventory version 2", header[0]
    return {line.split(" ", 1)[0] for line in zlib.decompress(header[4]).decode().splitlines() if line.strip()}


def api_entries() -> list[str]:
    """Every `::: name` entry of the API pages."""
    return [m for page in sorted((ROOT / "docs" / "api").rglob("*.md"))
            for m in re.findall(r"^::: *(\S+)", page.read_text(), flags=re.M)]


def test_fitting_all_is_its_lazy_names_and_its_static_imports():
    """`fitting.__all__` is what it loads lazily, and its `if TYPE_CHECKING:` block (what static readers such as the
    API reference's griffe see) imports each of those names; `piezojax.__all__` is every public name it binds."""
    import ast

    import fitting
    import piezojax

    assert sorted(fitting.__all__) == sorted(fitting._LAZY)
    assert not [n for n in fitting.__all__ if n.startswith("_")]
    tree = ast.parse((ROOT / "fitting" / "__init__.py").read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    static = {a.asname or a.name for n in ast.walk(block) if isinstance(n, ast.ImportFrom) for a in n.names}
    assert static == set(fitting.__all__)
    bound = {n for n, v in vars(piezojax).items() if not n.startswith("_") and not isinstance(v, types.ModuleType)}
    assert sorted(piezojax.__all__) == sorted(bound)


def test_every_public_name_has_one_api_entry():
    import fitting
    import piezojax

    entries = api_entries()
    expected = [f"piezojax.{n}" for n in public_names(piezojax)] + [f"fitting.{n}" for n in public_names(fitting)]
    duplicated = sorted({e for e in entries if entries.count(e) > 1})
    assert not duplicated, f"documented more than once: {duplicated}"
    assert not sorted(set(expected) - set(entries)), f"no API entry: {sorted(set(expected) - set(entries))}"
    assert not sorted(set(entries) - set(expected)), f"not a public name: {sorted(set(entries) - set(expected))}"
    assert len(public_names(piezojax)) > 80 and len(public_names(fitting)) > 60  # the check sees the real names


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site built once (one test uses it, so that pytest-xdist does not build it in two workers)."""
    missing = [p for p in DOCS_PACKAGES if importlib.util.find_spec(p.split(".")[0]) is None
               or importlib.util.find_spec(p) is None]
    if missing:
        pytest.skip(f"the docs extra is not installed (pip install -e '.[docs]'): no {', '.join(missing)}")
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, f"mkdocs build --strict failed:\n{run.stdout[-4000:]}\n{run.stderr[-8000:]}"
    return out


def test_site_builds_strictly_and_its_inventory_holds_every_public_name(site):
    import fitting
    import piezojax

    inventory = read_inventory(site / "objects.inv")
    missing = [f"piezojax.{n}" for n in public_names(piezojax) if f"piezojax.{n}" not in inventory]
    missing += [f"fitting.{n}" for n in public_names(fitting) if f"fitting.{n}" not in inventory]
    assert not missing, f"not in the built inventory (objects.inv): {missing}"
    # the pages around the reference are there too: the tutorials (the notebooks, not executed) and the gallery
    assert (site / "notebooks" / "01_quickstart" / "index.html").exists()
    assert (site / "gallery" / "fit_150v_loops.png").exists()
    assert "Prandtl" in (site / "api" / "piezojax" / "hysteresis" / "index.html").read_text()

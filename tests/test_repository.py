"""The README's commands are a contract: CI must run exactly the README's test command."""

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]


def readme_commands():
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```bash\n(.*?)\n```", text, flags=re.S)


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    test_commands = [c for c in readme_commands() if "pytest" in c]
    assert len(test_commands) == 1, "the README must give exactly one test command"
    assert test_commands[0].strip() in ci.splitlines()


def test_package_does_not_change_global_jax_config():
    import subprocess
    import sys

    code = ("import jax, piezojax, fitting, fitting.cli; fitting.fit, fitting.Dataset, fitting.FitResult; "
            "print(jax.config.jax_enable_x64, jax.config.jax_numpy_dtype_promotion)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "standard"]


def test_fitting_imports_lazily_and_exports_every_name():
    import subprocess
    import sys

    code = ("import sys, fitting, fitting.cli; print('jax' in sys.modules); "
            "[getattr(fitting, n) for n in fitting._LAZY]; print(set(fitting._LAZY) <= set(dir(fitting)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "True"]  # the command line installs its signal handlers before JAX is imported


def _imports(path: pathlib.Path) -> set[str]:
    """The absolute module names `path` imports (relative imports resolved against its package)."""
    import ast

    package = list(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            out.add(module)
            out |= {f"{module}.{a.name}" for a in node.names}
    return out


FOUNDATIONS = {"_checks", "_dtypes", "_custom_types", "_parametrisation", "_config", "_scans"}
# What each folder may import from the library (README, "Layout"); a new edge is a design decision, not an accident.
ALLOWED = {
    "piezojax._hysteresis": {"piezojax._checks", "piezojax._custom_types", "piezojax._dtypes", "piezojax._hysteresis",
                             "piezojax._parametrisation", "piezojax._config", "piezojax._scans"},
    "piezojax._linear": {"piezojax._checks", "piezojax._custom_types", "piezojax._dtypes", "piezojax._linear",
                         "piezojax._config", "piezojax._scans"},
    "piezojax._nonlinear": {"piezojax._checks", "piezojax._custom_types", "piezojax._dtypes", "piezojax._nonlinear",
                            "piezojax._linear"},
    "piezojax._creep": {"piezojax._checks", "piezojax._custom_types", "piezojax._dtypes", "piezojax._creep",
                        "piezojax._linear", "piezojax._hysteresis.play", "piezojax._config", "piezojax._scans"},
    "piezojax._circuits": {"piezojax._checks", "piezojax._custom_types", "piezojax._dtypes", "piezojax._circuits",
                           "piezojax._linear", "piezojax._hysteresis.base", "piezojax._creep.base"},
    "piezojax._control": {"piezojax._checks", "piezojax._custom_types", "piezojax._dtypes", "piezojax._control",
                          "piezojax._parametrisation"},
    "piezojax._observers": {"piezojax._checks", "piezojax._custom_types", "piezojax._dtypes", "piezojax._observers",
                            "piezojax._circuits", "piezojax._linear", "piezojax._hysteresis.base",
                            "piezojax._creep.base"},
}


# `fitting` uses the library through `piezojax` and its semi-public `piezojax.internal` only (README, Layout: fitting)
FITTING_ALLOWED: set[str] = set()


def _private_name_of_another_part(path: pathlib.Path, name: str) -> bool:
    """Whether `name`, imported by `path` inside `fitting`, is a private name (not a module) defined in another part of
    `fitting`: a flat module other than `path`, or a package other than the one `path` sits in. Within a package its
    modules share private helpers, as equinox's and optimistix's do."""
    parts = name.split(".")
    if parts[0] != "fitting" or parts[-1][:1] != "_" or parts[-1].startswith("__"):
        return False
    module = ROOT.joinpath(*parts[:-1])
    if (ROOT.joinpath(*parts).with_suffix(".py").exists() or ROOT.joinpath(*parts).is_dir()
            or not (module.with_suffix(".py").exists() or module.is_dir())):
        return False  # a module or package, not a name defined in one
    own = path.relative_to(ROOT).with_suffix("").parts
    return parts[:2] != list(own[:2]) or len(own) == 2 and own[1] != "__init__" and parts[:-1] != list(own)


def test_layers_import_only_what_the_layout_allows():
    problems = []
    for folder, allowed in ALLOWED.items():
        for path in sorted((ROOT / folder.replace(".", "/")).glob("*.py")):
            for name in _imports(path):
                if name == "piezojax":  # the package itself, i.e. everything (`from .. import x` is seen as piezojax.x)
                    problems.append(f"{path.relative_to(ROOT)} imports the whole package")
                elif name.startswith("piezojax.") and not any(name == a or name.startswith(a + ".") for a in allowed):
                    problems.append(f"{path.relative_to(ROOT)} imports {name}")
    # fitting and the experiments use the library, never its benches' private code
    # the foundations import no family except through the composed `Actuator` (and its inverse) and the public
    # namespace
    for path in sorted((ROOT / "piezojax").glob("_*.py")):
        if path.name in ("__init__.py", "_actuator.py", "_actuator_inverse.py"):
            continue
        for name in _imports(path):
            if name.startswith("piezojax._") and name.split(".")[1] not in FOUNDATIONS:
                problems.append(f"{path.relative_to(ROOT)} (a foundation) imports {name}")
    for path in sorted((ROOT / "fitting").rglob("*.py")) + sorted((ROOT / "experiments").glob("*.py")):
        in_fitting = path.relative_to(ROOT).parts[0] == "fitting"
        for name in _imports(path):
            if name.startswith("piezojax._benches"):
                problems.append(f"{path.relative_to(ROOT)} imports {name}")
            if in_fitting and name.startswith("piezojax._") and not name.startswith(
                    "piezojax.__") and not any(
                    name == a or name.startswith(a + ".") for a in FITTING_ALLOWED):
                problems.append(f"{path.relative_to(ROOT)} imports {name} (README, Layout: fitting)")
            if in_fitting and _private_name_of_another_part(path, name):
                problems.append(f"{path.relative_to(ROOT)} imports the private name {name} of another module")
            if path.parent.name == "experiments" and name.startswith("fitting._"):
                problems.append(f"{path.relative_to(ROOT)} imports {name} (use fitting's public API)")
    assert not problems, "\n".join(problems)
    # the check sees real edges (a resolver that saw none would pass vacuously)
    assert "piezojax.internal.lag_columns" in _imports(ROOT / "fitting" / "_staged.py")
    assert "piezojax._linear.base" in _imports(ROOT / "piezojax" / "_creep" / "linear.py")


def test_no_concrete_method_is_overridden():
    """equinox's abstract/final pattern: a method is abstract or final, never a concrete default overridden below."""
    import importlib
    import inspect
    import pkgutil

    import equinox as eqx

    import fitting
    import piezojax

    ours = ("piezojax", "fitting")
    classes = set()
    for package in (piezojax, fitting):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            module = importlib.import_module(info.name)
            for _, cls in inspect.getmembers(module, inspect.isclass):
                if issubclass(cls, eqx.Module) and cls.__module__.split(".")[0] in ours:
                    classes.add(cls)
    problems = []
    for cls in sorted(classes, key=lambda c: f"{c.__module__}.{c.__qualname__}"):
        for name, value in vars(cls).items():
            if name.startswith("__") and name != "__call__":
                continue
            if not (inspect.isfunction(value) or isinstance(value, property)):
                continue
            if getattr(value, "__isabstractmethod__", False):
                continue
            for base in cls.__mro__[1:]:
                if base.__module__.split(".")[0] not in ours or name not in vars(base):
                    continue
                if not getattr(vars(base)[name], "__isabstractmethod__", False):
                    problems.append(f"{cls.__module__}.{cls.__qualname__}.{name} overrides {base.__qualname__}.{name}")
                break
    assert not problems, "\n".join(problems)
    # the check saw the library's classes (one that found none would pass vacuously)
    assert len(classes) > 30, f"only {len(classes)} Module classes found"
    assert piezojax.PrandtlIshlinskii in classes and piezojax.AbstractHysteresis in classes


# ------------------------------------------------------------------------------------------ the layout's limits

MAX_FILE_LINES = 500  # lines of code in a module (docstrings, comments and blank lines not counted)
MAX_FUNCTION_LINES = 100  # lines of code in a function


def _code_lines(source: str, tree) -> set[int]:
    """The line numbers of `source` that hold code: not a docstring, a comment or a blank line."""
    import ast
    import io
    import tokenize

    docs = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(
                    first.value.value, str):
                docs |= set(range(first.lineno, first.end_lineno + 1))
    skip = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER}
    lines = set()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type not in skip:
            lines |= set(range(tok.start[0], tok.end[0] + 1))
    return lines - docs


def _modules(package: str) -> dict[str, pathlib.Path]:
    """Every module of `package` by its dotted name (a package by its own name, for its `__init__.py`)."""
    out = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _import_edges(package: str) -> tuple[dict[str, set[str]], list[str]]:
    """`(edges, inner)`: the modules of `package` each module imports when it is loaded (a name imported from a package
    counts as its submodule when it is one), and the imports of sibling modules inside functions (as `"a -> b"`).
    Imports under `if TYPE_CHECKING:` are not made at run time and count as neither."""
    import ast

    modules = _modules(package)
    edges: dict[str, set[str]] = {m: set() for m in modules}
    inner = []
    for name, path in modules.items():
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        tree = ast.parse(path.read_text())
        typing_only = {id(n) for t in tree.body if isinstance(t, ast.If) and "TYPE_CHECKING" in ast.dump(t.test)
                       for n in ast.walk(t)}
        functions = {id(n) for f in ast.walk(tree) if isinstance(f, ast.FunctionDef | ast.AsyncFunctionDef)
                     for n in ast.walk(f)}
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = parts[: len(parts) - node.level] if node.level else []
                module = ".".join(base + ([node.module] if node.module else []))
                targets = [f"{module}.{a.name}" for a in node.names if f"{module}.{a.name}" in modules] or [module]
            else:
                continue
            for target in targets:
                if target not in modules or target == name:
                    continue
                if id(node) in functions:
                    inner.append(f"{name} -> {target}")
                else:
                    edges[name].add(target)
    return edges, inner


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of `edges`: its strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in edges:
        if v not in index:
            visit(v)
    return out


def test_no_file_or_function_is_too_long():
    """No module of the library or of `fitting` over 500 lines of code, no function over 100."""
    import ast

    problems = []
    for package in ("piezojax", "fitting"):
        for path in _modules(package).values():
            source = path.read_text()
            tree = ast.parse(source)
            lines = _code_lines(source, tree)
            if len(lines) > MAX_FILE_LINES:
                problems.append(f"{path.relative_to(ROOT)}: {len(lines)} lines of code")
            for node in ast.walk(tree):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    n = len([k for k in lines if node.lineno <= k <= node.end_lineno])
                    if n > MAX_FUNCTION_LINES:
                        problems.append(f"{path.relative_to(ROOT)}:{node.name}: {n} lines of code")
    assert not problems, "\n".join(problems)


def test_no_import_cycle_and_no_import_inside_a_function():
    """The modules of `piezojax` and `fitting` import each other one way only, and at module level: a sibling module is
    imported inside a function only by the command line (which installs its signal handlers before JAX is loaded)
    and by `fitting/__init__.py`'s lazy loading."""
    for package in ("piezojax", "fitting"):
        edges, inner = _import_edges(package)
        assert not _cycles(edges), _cycles(edges)
        inner = [i for i in inner if not i.startswith(("fitting.cli", "fitting -> "))]
        assert not inner, "\n".join(inner)
    # the checks see what they look for: a cycle in a made-up graph, the command line's deferred imports, the
    # module-level edges of the real layout
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    edges, inner = _import_edges("fitting")
    assert any(i.startswith("fitting.cli.commands -> fitting._calibrate") for i in inner)
    assert "fitting._data.formats" in edges["fitting._data.dataset"]
    assert "fitting.files" in edges["fitting._calibrate"]  # `from . import files`
    assert _code_lines('"""doc"""\n\n# comment\nx = 1\n', __import__("ast").parse('"""doc"""\n\n# comment\nx = 1\n')) \
        == {4}


# What each part of `fitting` may import from the others (README, Layout: fitting): the data at the bottom, the
# command line at the top. A new edge is a design decision: add it here and to the README.
FITTING_LAYERS = {
    "files": set(),
    "_timing": set(),
    "_data": {"files"},
    "_predict": {"_data"},
    "_plots": {"_data"},
    "_initialise": {"_data"},
    "_staged": {"_data"},
    "_problem": {"_data", "_predict"},
    "_solver": {"_problem"},
    "_stationarity": {"_problem", "_solver"},
    "_config": {"_data", "_initialise", "_predict", "_problem"},
    "_results": {"_config", "_data", "_plots", "_predict", "_problem", "_stationarity", "files"},
    "_solve": {"_problem", "_results", "_solver", "_stationarity"},
    "_fleet": {"_data", "_problem", "_results", "_solve", "_solver"},
    "_refine": {"_config", "_problem", "_solve", "_solver"},
    "_calibrate": {"_config", "_data", "_problem", "_refine", "_results", "_solve", "_timing", "files"},
    "_fit_folder": {"_config", "_data", "_problem", "_results"},
    "_warm_up": {"_data", "_predict"},
    "_identify": {"_calibrate", "_config", "_data", "_predict", "_problem", "_refine", "_results", "files"},
    "cli": {"__init__", "_calibrate", "_config", "_data", "_identify", "_results", "_timing", "files"},
    "__init__": set(),  # its lazy loading reaches every part by name, not by import
}


def test_each_part_of_fitting_imports_only_the_parts_below_it():
    edges, inner = _import_edges("fitting")

    def part(module):
        parts = module.split(".")
        return parts[1] if len(parts) > 1 else "__init__"

    pairs = {(part(a), part(b)) for a, bs in edges.items() for b in bs}
    pairs |= {(part(a), part(b)) for a, b in (i.split(" -> ") for i in inner)}
    unknown = sorted({p for pair in pairs for p in pair} - set(FITTING_LAYERS))
    assert not unknown, f"parts of fitting not in FITTING_LAYERS: {unknown}"
    problems = sorted(f"fitting.{a} imports fitting.{b}" for a, b in pairs if a != b and b not in FITTING_LAYERS[a])
    assert not problems, "\n".join(problems)
    assert ("_calibrate", "_refine") in pairs and ("cli", "_calibrate") in pairs  # the check sees real edges

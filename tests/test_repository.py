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

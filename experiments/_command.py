"""What the reproductions' command lines share: the output folder, the exit status and the argument types.

- **The output folder** (`--out`) is checked before any work (`output_folder`), written whole or not at all, and
  replaces only an earlier output of the same experiment (`writing`: `fitting.files.atomic_directory` with the
  experiment as its `kind`, so the folder carries the marker file): a folder of the user's, or one holding a file
  the experiment did not write, is refused, naming it, and nothing is deleted.
- **The exit status** (`run`): 0 done, 2 bad input (one line naming the argument, file or key), 130 interrupted
  (Ctrl-C; nothing written). A fit stopped by Ctrl-C returns its last point as a result with code
  `"interrupted"`; `stop_if_interrupted` turns it back into the interrupt, so that no table, figure or file is made
  from a fit the user stopped.
- **Argument types** that refuse nonsense when the command line is read (argparse: exit 2): `positive_int`,
  `existing_file`.
"""

import argparse
import contextlib
import sys
from collections.abc import Callable, Iterator
from pathlib import Path


def positive_int(text: str) -> int:
    """An argparse type: an integer ≥ 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {n}")
    return n


def existing_file(text: str) -> Path:
    """An argparse type: the path of an existing file."""
    p = Path(text).expanduser()
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"no such file: {text!r}" if not p.exists() else f"not a file: {text!r}")
    return p


def output_folder(path: str, kind: str, default: str | None = None) -> Path:
    """Check the output folder `path` now, before any work, as `writing` will write it; returns its absolute path.

    Refused (`PiezojaxValueError`, naming the folder): an empty path, a folder whose parent does not exist (the
    parents of the experiment's `default` folder, e.g. `results/` in a fresh clone, are made), the working
    directory or one above it, and an existing folder that is not an earlier output of experiment `kind` or holds
    something that output did not write.
    """
    import fitting

    if default is not None and path == default:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    p = fitting.files.check_writable(path)
    fitting.files.check_replaceable_directory(p, True, kind, option="running it again")
    return p


@contextlib.contextmanager
def writing(out: Path, kind: str) -> Iterator[Path]:
    """The temporary folder to write every output file into; it becomes `out` on normal exit (see the module
    docstring), and on an exception `out` is left as it was."""
    import fitting

    with fitting.files.atomic_directory(out, overwrite=True, kind=kind) as tmp:
        yield tmp


def stop_if_interrupted(result) -> None:
    """Raise `KeyboardInterrupt` if the `fitting.FitResult` `result` is a fit the user stopped (Ctrl-C)."""
    if result.code == "interrupted":
        raise KeyboardInterrupt


def run(main: Callable[[], object], prog: str) -> int:
    """Call `main()` and return the exit status: 0, 2 with one line on a `PiezojaxValueError` (bad input), 130 on
    Ctrl-C."""
    from piezojax import PiezojaxValueError

    try:
        main()
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; nothing written", file=sys.stderr)
        return 130
    except PiezojaxValueError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    return 0

"""`python -m fitting.cli`: the `piezojax` command."""

from .program import console_main

if __name__ == "__main__":
    console_main()

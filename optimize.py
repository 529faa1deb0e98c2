#!/usr/bin/env python3
"""Fit a NeRF++ to posed images: ``python optimize.py [DATA] [options]``.

Without DATA, the embedded default scene is synthesized (once) and trained for about
ten minutes. Same as ``python -m mi_nerfpp optimize``; ``--help`` lists the options.
"""
import sys

from mi_nerfpp._start import run_and_exit
from mi_nerfpp.commands.cli import main

if __name__ == '__main__':
    run_and_exit(main, ['optimize'] + sys.argv[1:], replace=True)

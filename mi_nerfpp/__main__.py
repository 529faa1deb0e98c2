"""``python -m mi_nerfpp <command>``: the command line (:mod:`mi_nerfpp.commands.cli`)."""
import sys

from mi_nerfpp.commands.cli import main

sys.exit(main())

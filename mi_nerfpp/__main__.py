"""``python -m mi_nerfpp <command>``: the command line (:mod:`mi_nerfpp.commands.cli`)."""
from mi_nerfpp.commands.cli import entry_point

entry_point()

import sys

from mi_nerfpp.commands.cli import main

sys.exit(main())

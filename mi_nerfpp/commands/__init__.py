"""The commands of ``python -m mi_nerfpp``: one module per command, each with
``add_parser(subparsers)`` and ``run(args)`` (:mod:`.cli` gathers them); library code lives in the
layers below."""

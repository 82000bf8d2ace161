"""Command line: ``canrls SUBCOMMAND``, one module per subcommand.

Each subcommand module defines ``add_subparser(subparsers)`` which registers its
parser and sets ``func`` (a callable taking the parsed namespace and returning the
exit code). A module whose optional dependency is missing disables only itself.
"""

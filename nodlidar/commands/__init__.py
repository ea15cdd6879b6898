"""CLI subcommands, one module each.

Every module here defines ``register(subparsers)`` that adds its subparser and sets
``func=run`` where ``run(args) -> int``. :mod:`nodlidar.cli` discovers them, so adding a
command never means editing a shared file. Keep heavy imports inside ``run``.
"""

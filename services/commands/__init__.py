"""Sub-commands of ``msk``: every module here that defines ``register(subparsers)`` adds one or more commands.

Modules are discovered at start-up so that adding a command never means editing a shared list.
"""

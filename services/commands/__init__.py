"""Sub-commands of ``msk``: every module here that defines ``register(subparsers)`` adds one or more commands.

Modules are discovered at start-up so that adding a command never means editing a shared list. Which commands a
module adds is read from its source (:func:`declared_commands`, no import), so ``msk X`` imports only the module that
registers ``X`` and ``msk --help`` imports none: several modules pull in the whole estimation stack (scipy, numba,
pinocchio: ~2 s), and every ``msk`` subprocess (a live session starts several) would pay for all of them. So
``register`` names its commands with literals, ``subparsers.add_parser("name", help="...", aliases=[...])``
(tests/test_cli.py checks that what is read equals what ``register`` adds).
"""

from __future__ import annotations

import argparse
import ast
from dataclasses import dataclass
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent


def described(parser: argparse.ArgumentParser, doc: str | None) -> argparse.ArgumentParser:
    """``parser`` (a command's, from ``subparsers.add_parser``) with ``doc`` (its module's docstring) as its
    description, shown as written in ``--help``: line breaks, lists and tables kept rather than re-wrapped."""
    parser.description = doc
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    return parser


@dataclass(frozen=True)
class DeclaredCommand:
    """One ``subparsers.add_parser(NAME, help=HELP, aliases=[...])`` call of a module's ``register``."""

    name: str
    help: str | None
    aliases: tuple[str, ...]


@dataclass(frozen=True)
class CommandModule:
    """A module of this package with a ``register(subparsers)``; ``commands`` is None when its source does not say
    its commands as literals (the command line then imports it to find out)."""

    module: str
    commands: tuple[DeclaredCommand, ...] | None

    def declares(self, word: str) -> bool:
        return self.commands is None or any(word == c.name or word in c.aliases for c in self.commands)


def _literal_strings(node: ast.expr) -> tuple[str, ...] | None:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return (node.value,)
    if isinstance(node, ast.List | ast.Tuple):
        parts = [_literal_strings(e) for e in node.elts]
        return None if any(p is None or len(p) != 1 for p in parts) else tuple(p[0] for p in parts if p)
    return None


def _declared(call: ast.Call) -> DeclaredCommand | None:
    """The command one ``add_parser`` call adds, or None when its name, help or aliases are not literals."""
    name = _literal_strings(call.args[0]) if len(call.args) == 1 else None
    keywords = {k.arg: k.value for k in call.keywords}
    help_text = _literal_strings(keywords["help"]) if "help" in keywords else (None,)
    aliases = _literal_strings(keywords["aliases"]) if "aliases" in keywords else ()
    if name is None or help_text is None or aliases is None or None in keywords:  # None: **kwargs
        return None
    return DeclaredCommand(name[0], help_text[0], aliases)


def _commands_of(tree: ast.Module) -> tuple[DeclaredCommand, ...] | None:
    """The commands the module-level ``register(subparsers)`` adds (``subparsers.add_parser`` calls), in order."""
    register = next((n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "register"), None)
    if register is None or not register.args.args:
        return None
    param = register.args.args[0].arg
    found: list[tuple[int, int, DeclaredCommand]] = []
    for node in ast.walk(register):
        if isinstance(node, ast.Name) and node.id == param and not isinstance(node.ctx, ast.Load):
            return None  # the parameter is rebound: the calls below cannot be read from the source
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_parser":
            if isinstance(node.func.value, ast.Name) and node.func.value.id == param:
                command = _declared(node)
                if command is None:
                    return None
                found.append((node.lineno, node.col_offset, command))
    return tuple(command for _, _, command in sorted(found, key=lambda f: f[:2]))


def command_modules(word: str | None = None) -> list[CommandModule]:
    """The modules of this package that define ``register``, sorted by name, with the commands each adds; with
    ``word``, only those that may add a command (or alias) of that name (a cheap text check before parsing)."""
    modules: list[CommandModule] = []
    for path in sorted(PACKAGE_DIR.glob("*.py")):
        if path.stem.startswith("_"):
            continue
        text = path.read_text(encoding="utf-8")
        if "def register(" not in text or (word is not None and f'"{word}"' not in text and f"'{word}'" not in text):
            continue
        tree = ast.parse(text, filename=str(path))
        if not any(isinstance(n, ast.FunctionDef) and n.name == "register" for n in tree.body):
            continue
        module = CommandModule(f"{__name__}.{path.stem}", _commands_of(tree))
        if word is None or module.declares(word):
            modules.append(module)
    return modules

"""Old module paths that still import, with a warning that names the new one.

A package whose modules moved (``satloc.georef`` is now ``satloc.geodata.georef``; ``satloc_env.env`` is
``satloc_env.envs.drive``) calls :func:`alias_modules` with a table ``{old name: new name}``. ``import old``,
``from old import x`` and ``package.old`` (an attribute of the imported package) then give the new module
itself (one module object, so a class is the same class under both names) and emit one
:class:`FutureWarning` per old name saying where it lives now. The tables are in each package's
``__init__`` and in ``CHANGELOG.md``.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings

__all__ = ["alias_modules"]


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, new: str):
        self.new = new

    def create_module(self, spec):
        module = importlib.import_module(self.new)
        self.own_spec = module.__spec__
        return module

    def exec_module(self, module):
        # the new module is already executed; the import system has just set its __spec__ to the alias's:
        # give it back its own (its __name__ is untouched)
        module.__spec__ = self.own_spec


class _AliasFinder(importlib.abc.MetaPathFinder):
    def __init__(self, aliases: dict[str, str]):
        self.aliases = dict(aliases)

    def find_spec(self, fullname, path=None, target=None):
        new = self.aliases.get(fullname)
        if new is None:
            return None
        _warn(fullname, new, stacklevel=4)
        return importlib.machinery.ModuleSpec(fullname, _AliasLoader(new))


def _warn(old: str, new: str, stacklevel: int) -> None:
    warnings.warn(f"{old} moved to {new}; import it from there (the old name goes in a later version)",
                  FutureWarning, stacklevel=stacklevel)


def alias_modules(package: str, aliases: dict[str, str]):
    """Make each old module name of ``aliases`` import the new one; returns a module-level ``__getattr__``
    for ``package`` that resolves ``package.<old leaf>`` the same way."""
    sys.meta_path.append(_AliasFinder(aliases))
    leaves = {old.rpartition(".")[2]: old for old in aliases if old.rpartition(".")[0] == package}

    def __getattr__(name: str):
        old = leaves.get(name)
        if old is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return importlib.import_module(old)
    return __getattr__

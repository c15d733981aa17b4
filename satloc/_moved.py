"""Old module paths that still import, with a warning that names the new one.

A package whose modules moved (``satloc.georef`` is now ``satloc.geodata.georef``; ``satloc_env.env`` is
``satloc_env.envs.drive``) calls :func:`alias_modules` with a table ``{old name: new name}``. ``import old``,
``from old import x`` and ``package.old`` (an attribute of the imported package) then give the new module
itself (one module object, so a class is the same class under both names) and emit one
:class:`FutureWarning`, at the line that used the old name, saying where it lives now. ``python -m old``
stops with an error naming the new module. The tables are in each package's ``__init__`` and in
``CHANGELOG.md``.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings

__all__ = ["alias_modules"]

#: one finder per package (calling alias_modules again, e.g. on a reload, replaces it)
_FINDERS: dict[str, "_AliasFinder"] = {}


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, old: str, new: str):
        self.old, self.new = old, new

    def create_module(self, spec):
        module = importlib.import_module(self.new)
        self.own_spec = module.__spec__
        return module

    def exec_module(self, module):
        # the new module is already executed; the import system has just set its __spec__ to the alias's:
        # give it back its own (its __name__ is untouched)
        module.__spec__ = self.own_spec

    def get_code(self, fullname):   # what ``python -m old`` asks for
        raise ImportError(f"{self.old} moved to {self.new}: run python -m {self.new}")


class _AliasFinder(importlib.abc.MetaPathFinder):
    def __init__(self, aliases: dict[str, str]):
        self.aliases = dict(aliases)

    def find_spec(self, fullname, path=None, target=None):
        new = self.aliases.get(fullname)
        if new is None:
            return None
        # 1: _warn, 2: here, then the import system's own frames (which warnings skip), 3: the import statement
        _warn(fullname, new, stacklevel=3)
        return importlib.machinery.ModuleSpec(fullname, _AliasLoader(fullname, new))


def _warn(old: str, new: str, stacklevel: int) -> None:
    warnings.warn(f"{old} moved to {new}; import it from there (the old name goes in a later version)",
                  FutureWarning, stacklevel=stacklevel)


def alias_modules(package: str, aliases: dict[str, str]):
    """Make each old module name of ``aliases`` import the new one; returns a module-level ``__getattr__``
    for ``package`` that resolves ``package.<old leaf>`` the same way."""
    old = _FINDERS.pop(package, None)
    if old is not None and old in sys.meta_path:
        sys.meta_path.remove(old)
    finder = _FINDERS[package] = _AliasFinder(aliases)
    sys.meta_path.append(finder)
    leaves = {o.rpartition(".")[2]: o for o in aliases if o.rpartition(".")[0] == package}

    def __getattr__(name: str):
        o = leaves.get(name)
        if o is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = sys.modules.get(o)
        if module is None:
            _warn(o, aliases[o], stacklevel=3)      # 1: _warn, 2: here, 3: the line that read package.<name>
            module = importlib.import_module(aliases[o])
            sys.modules[o] = module
        return module
    return __getattr__


def forward_names(package: str, modules: tuple[str, ...]):
    """A module-level ``__getattr__`` for a package that replaced a module of the same name: a name the old
    module had beyond what the package re-exports resolves in ``modules`` (the new homes, in order), with a
    :class:`FutureWarning` naming where it lives now."""
    def __getattr__(name: str):
        if not name.startswith("__"):
            for m in modules:
                mod = importlib.import_module(m)
                if hasattr(mod, name):
                    warnings.warn(f"{package}.{name} moved to {m}.{name}; import it from there (the old name goes "
                                  "in a later version)", FutureWarning, stacklevel=2)
                    return getattr(mod, name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")
    return __getattr__

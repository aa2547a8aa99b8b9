"""A griffe extension (mkdocs.yml: the python handler's `extensions`) for the API page.

- Each `equinox.Module` (and `typing.NamedTuple`) of jaxlens gets the `__init__` that
  equinox (or `NamedTuple`) writes for it, so the page shows its constructor's
  signature. Equinox builds a dataclass `__init__` from the annotated fields at import
  time; griffe reads the source and, not knowing that `eqx.Module` is a dataclass,
  finds no `__init__` at all (its own dataclass support looks for `@dataclass`). The
  fields, in the order equinox takes them (the bases' first, a redefinition keeping its
  first place): annotated class attributes, less `ClassVar`s, `eqx.AbstractVar`s and
  `eqx.AbstractClassVar`s (which a subclass fills) and `eqx.field(init=False)`; the
  default from `= value` or `eqx.field(default=...)`. A class with an `__init__` of its
  own keeps it; an abstract base (`Abstract*`, which cannot be built) gets none. A
  `NamedTuple`'s fields are its annotated attributes, in order.
- A module attribute bound to a class (`SceneKey = Key`) is documented as that class.
- A module constant with no docstring takes its comment (the one on its line, else the
  comment lines right above it or above the run of one-line constants it ends), so
  `B_CRIT = ...  # critical impact parameter ...` reads on the page as in the source.
"""

import re

import griffe

_MODULE = ("equinox.Module", "typing.NamedTuple")
_ABSTRACT = ("equinox.AbstractVar", "equinox.AbstractClassVar")


def _path(expr) -> str:
    return getattr(expr, "canonical_path", str(expr))


def _is_module(cls: griffe.Class, seen: frozenset = frozenset()) -> bool:
    """Whether `cls` derives from `equinox.Module` (or is a `NamedTuple`), through bases
    griffe can resolve."""
    for base in cls.bases:
        if _path(base) in _MODULE:
            return True
        try:
            parent = cls.modules_collection.get_member(_path(base))
        except (KeyError, ValueError, AttributeError):
            continue
        if isinstance(parent, griffe.Alias):
            try:
                parent = parent.final_target
            except griffe.AliasResolutionError:
                continue
        if isinstance(parent, griffe.Class) and parent.path not in seen:
            if _is_module(parent, seen | {cls.path}):
                return True
    return False


def _call_args(expr) -> dict:
    """Keyword arguments of an `eqx.field(...)` value, as griffe expressions."""
    if isinstance(expr, griffe.ExprCall) and _path(expr.function).endswith(
        ("equinox.field", "dataclasses.field")
    ):
        return {
            arg.name: arg.value for arg in expr.arguments if isinstance(arg, griffe.ExprKeyword)
        }
    return {}


def _own_fields(cls: griffe.Class) -> dict[str, griffe.Parameter | None]:
    """The class's own annotated attributes: a parameter, or None for one that is not a
    field of `__init__` (a class variable or an abstract variable)."""
    fields = {}
    for member in cls.members.values():
        if member.is_alias or not member.is_attribute or member.annotation is None:
            continue
        if "property" in member.labels:
            continue
        annotation = member.annotation
        classvar = "class-attribute" in member.labels and "instance-attribute" not in member.labels
        abstract = (
            isinstance(annotation, griffe.ExprSubscript) and _path(annotation.left) in _ABSTRACT
        )
        args = _call_args(member.value)
        if classvar or abstract or str(args.get("init", "True")) == "False":
            fields[member.name] = None
            continue
        if "default_factory" in args:
            default = griffe.ExprCall(function=args["default_factory"], arguments=[])
        elif args:
            default = args.get("default")
        else:
            default = member.value
        fields[member.name] = griffe.Parameter(
            member.name,
            annotation=annotation,
            kind=griffe.ParameterKind.positional_or_keyword,
            default=default,
        )
    return fields


def _chain(cls: griffe.Class) -> list[griffe.Class]:
    try:
        return [*reversed(cls.mro()), cls]
    except ValueError:
        return [cls]


class EquinoxInit(griffe.Extension):
    """Adds the generated `__init__` to every `equinox.Module` and `NamedTuple` without
    one."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        _class_aliases(pkg)
        _comment_docstrings(pkg)
        for cls in _classes(pkg):
            if cls.name.startswith("Abstract") or _has_init(cls) or not _is_module(cls):
                continue  # an abstract base is not built: no signature
            fields: dict[str, griffe.Parameter | None] = {}
            for parent in _chain(cls):
                for name, param in _own_fields(parent).items():
                    if param is None and name in fields:
                        del fields[name]
                    elif param is None:
                        continue
                    else:
                        fields[name] = param
            init = griffe.Function(
                "__init__",
                lineno=0,
                endlineno=0,
                parent=cls,
                parameters=griffe.Parameters(
                    griffe.Parameter("self", kind=griffe.ParameterKind.positional_or_keyword),
                    *fields.values(),
                ),
                returns="None",
            )
            init.extra["jaxlens"]["generated"] = True
            cls.set_member("__init__", init)


def _has_init(cls: griffe.Class) -> bool:
    """Whether the class or a base defines `__init__` by hand (equinox then keeps it)."""
    for parent in _chain(cls):
        init = parent.members.get("__init__")
        if init is not None and not init.extra["jaxlens"].get("generated"):
            return True
    return False


def _classes(obj):
    for member in obj.members.values():
        if member.is_alias:
            continue
        if member.is_class:
            yield member
            yield from _classes(member)
        elif member.is_module:
            yield from _classes(member)


def _class_aliases(obj) -> None:
    """A module attribute bound to a class of the same module (`SceneKey = Key`) becomes
    an alias of that class, so the API page documents the class under the public name
    (griffe would show the assignment, with no docstring)."""
    for name, member in list(obj.members.items()):
        if member.is_alias:
            continue
        if member.is_module:
            _class_aliases(member)
        elif member.is_attribute and isinstance(member.value, griffe.ExprName):
            target = obj.members.get(member.value.name)
            if target is not None and not target.is_alias and target.is_class:
                obj.set_member(name, griffe.Alias(name, target, parent=obj))


def _comment_docstrings(obj) -> None:
    for member in list(obj.members.values()):
        if member.is_alias:
            continue
        if member.is_module:
            _comment_docstrings(member)
        elif member.is_attribute and member.docstring is None and member.lineno:
            text = _comment(obj.lines, member.lineno, member.endlineno or member.lineno)
            if text:
                member.docstring = griffe.Docstring(text, parent=member)


_CONSTANT = re.compile(r"^[A-Z][A-Z0-9_]* = [^#]*$")


def _comment(lines: list[str], first: int, last: int) -> str:
    """The comment of the statement on lines `first`..`last` (1-based): the one after
    the code on its last line, else the comment lines right above it."""
    code, sep, after = lines[last - 1].partition("  # ")
    if sep and after.strip():
        return after.strip()
    above = []
    i = first - 2
    while i >= 0 and _CONSTANT.match(lines[i]):
        i -= 1  # a run of one-line constants shares the comment above the first
    while i >= 0 and lines[i].lstrip().startswith("#"):
        above.insert(0, lines[i].strip().lstrip("#").strip())
        i -= 1
    return " ".join(above)

"""A griffe extension for the API reference (mkdocstrings), reading the docstrings as they
are written:

* they cross-reference in Sphinx's roles (``:func:`read_euroc```, ``:class:`ImuData```),
  which Markdown would print as they are: each role becomes the inline code of its target
  before the docstring is parsed;
* a paragraph that ends in ``::`` introduces an indented literal block (reStructuredText),
  which Markdown reads as a code block already: the ``::`` becomes ``:``;
* a few docstrings are completed when their module is imported (a shared paragraph put in
  place of ``{repair}``, ``{sensor}``, ``{coriolis}``): those are read from the imported
  object, as ``help()`` shows them;
* their ``Args:`` sections describe parameters that share a meaning together
  (``gyro, accel: (..., T, 3) ...``), which griffe's Google parser takes for one unknown
  name. The site's configuration turns griffe's own check off, and this one takes its place:
  every name of every entry must be a parameter of the signature, or the build (``--strict``)
  fails with griffe's warning.
"""

import importlib
import inspect
import re

import griffe

_LITERAL = re.compile(r"(?<=\S)::[ \t]*\n(?=[ \t]*\n)")
_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|obj|exc|const):`~?([^`]+)`")


def _plain(match):
    target = match.group(1)
    # Sphinx's explicit title form, ``:func:`title <target>```: keep the title
    titled = re.fullmatch(r"(.+?)\s*<[^>]+>", target)
    return f"`{titled.group(1) if titled else target}`"


_PLACEHOLDER = re.compile(r"\{[a-z_]+\}")


def _clean(text):
    return _LITERAL.sub(":\n", _ROLE.sub(_plain, text))


def _runtime_docstring(obj):
    """The docstring of ``obj`` once its module has run, or None where it cannot be imported."""
    try:
        module = importlib.import_module(obj.module.path)
    except ImportError as error:  # an optional dependency the site's environment lacks
        griffe.logger.warning("%s: %s", obj.relative_filepath, error)
        return None
    value = module
    for name in obj.path[len(obj.module.path) + 1 :].split("."):
        value = getattr(value, name, None)
    return inspect.getdoc(value) if value is not None else None


def _complete(obj):
    """Fill a docstring's placeholders from the imported object's docstring."""
    if obj.docstring is None or not _PLACEHOLDER.search(obj.docstring.value):
        return
    runtime = _runtime_docstring(obj)
    if runtime is not None and not _PLACEHOLDER.search(runtime):
        obj.docstring.value = _clean(runtime)
        return
    griffe.logger.warning(
        "%s:%s: docstring placeholder %s is not filled at import",
        obj.relative_filepath,
        obj.docstring.lineno,
        _PLACEHOLDER.search(obj.docstring.value).group(0),
    )


def _signature_names(obj):
    """The parameter names of a function, or of a class's ``__init__``; None when unknown."""
    try:
        params = obj.parameters
    except (AttributeError, griffe.AliasResolutionError):
        return None
    names = {p.name for p in params}
    return names | {f"*{n}" for n in names} | {f"**{n}" for n in names}


def _check_parameters(obj):
    if not (obj.is_function or obj.is_class) or obj.docstring is None:
        return
    names = _signature_names(obj)
    if not names:
        return
    docstring = obj.docstring
    for section in griffe.parse_google(docstring, warnings=False):
        if section.kind is not griffe.DocstringSectionKind.parameters:
            continue
        for param in section.value:
            for name in (n.strip() for n in param.name.split(",")):
                if name not in names:
                    griffe.logger.warning(
                        "%s:%s: Parameter '%s' does not appear in the function signature",
                        obj.relative_filepath,
                        docstring.lineno,
                        name,
                    )


def _public_objects(module, seen):
    """What the reference renders: the public members (``__all__`` where a module has one)
    of the public modules, followed through re-exports, and their methods."""
    for member in module.members.values():
        if member.name.startswith("_") and not member.is_module:
            continue
        try:
            target = member.final_target if member.is_alias else member
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        if target.path in seen:
            continue
        if target.is_module:
            if not member.name.startswith("_") and target.path.startswith(module.path + "."):
                seen.add(target.path)
                yield from _public_objects(target, seen)
            continue
        if not member.is_public:
            continue
        seen.add(target.path)
        yield target
        if target.is_class:
            for method in target.members.values():
                if not method.is_alias and method.is_function and not method.name.startswith("_"):
                    yield method


class Docstrings(griffe.Extension):
    """Sphinx roles as inline code, ``::`` as ``:``, placeholders filled; grouped ``Args:``
    entries checked name by name."""

    def on_instance(self, *, obj, **kwargs):
        if obj.docstring is not None:
            obj.docstring.value = _clean(obj.docstring.value)

    def on_package(self, *, pkg, **kwargs):
        for obj in _public_objects(pkg, {pkg.path}):
            _complete(obj)
            _check_parameters(obj)

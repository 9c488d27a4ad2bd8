"""One way to merge options over a stage's defaults (an unknown key, a typo, is a one-line error),
one spelling of an option that is off: None in Python, ``none`` on the command line, and command
line flags generated from a ``default_conf`` dict, its comments as their help."""

from __future__ import annotations

import argparse
import ast
import difflib
import inspect
import io
import textwrap
import tokenize
from collections.abc import Callable, Sequence
from typing import Any


def merge_conf(defaults: dict, conf: dict | None, what: str) -> dict:
    """``conf`` over ``defaults``; a key ``defaults`` does not have raises ValueError naming
    ``what``, the nearest known key and the known ones."""
    unknown = sorted(set(conf or {}) - set(defaults), key=str)
    if unknown:
        near = {
            key: close[0]
            for key in unknown
            if (close := difflib.get_close_matches(str(key), [str(k) for k in defaults], n=1))
        }
        if len(unknown) == 1:
            hint = f"; did you mean {near[unknown[0]]!r}?" if near else ";"
        else:
            hint = "; did you mean " + " and ".join(
                f"{near[key]!r} for {key!r}" for key in unknown if key in near
            )
            hint = hint + "?" if near else ";"
        keys = ", ".join(repr(key) for key in unknown)
        raise ValueError(
            f"Unknown {what} option{'s' if len(unknown) > 1 else ''} {keys}{hint} "
            f"known: {sorted(defaults)}"
        )
    return {**defaults, **(conf or {})}


def none_or(kind: Callable[[str], Any], old_off: Callable[[str], bool] | None = None):
    """An argparse type for an option that can be off: ``none`` (the one documented spelling) is
    None, other text ``kind(text)``. ``old_off``: the flag's other spellings of off (e.g. 0), read
    as None too so that existing command lines keep working."""

    def parse(text: str):
        text = text.strip()
        if text.lower() == "none" or (old_off is not None and old_off(text.lower())):
            return None
        return kind(text)

    parse.__name__ = getattr(kind, "__name__", "value")  # argparse's "invalid float value: ..."
    return parse


def at_most_zero(text: str) -> bool:
    """Whether a count or threshold given on the command line is 0 or below: off for the flags
    that read it so."""
    return float(text) <= 0


def conf_comments(owner, name: str = "default_conf") -> dict[str, str]:
    """The comment of each option of ``owner.<name>`` (``owner``: the module or class that assigns
    the dict literal) in its source: the comment lines directly above the key and a comment at the
    end of the key's line, joined."""
    tokens = list(
        tokenize.generate_tokens(io.StringIO(textwrap.dedent(inspect.getsource(owner))).readline)
    )
    body = 1 if inspect.isclass(owner) else 0  # the indentation level of the owner's statements
    skip = (tokenize.NL, tokenize.COMMENT)
    level, depth, start = 0, 0, None
    for i, tok in enumerate(tokens[:-2]):
        level += (tok.type == tokenize.INDENT) - (tok.type == tokenize.DEDENT)
        if tok.type == tokenize.OP and tok.string in "([{)]}":
            depth += 1 if tok.string in "([{" else -1
        before = tokens[i - 1].type if i else tokenize.NEWLINE
        statement = before in (tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.NL)
        if (level, depth, statement, tok.string) == (body, 0, True, name):
            if tokens[i + 1].string == "=" and tokens[i + 2].string == "{":
                start = i + 3
                break
    if start is None:
        raise ValueError(f"{getattr(owner, '__name__', owner)} assigns no {name} dict literal")
    comments: dict[str, list[str]] = {}
    above: list[str] = []
    depth, key, key_row = 1, None, -1
    for i in range(start, len(tokens)):
        tok = tokens[i]
        if tok.type == tokenize.OP and tok.string in "([{":
            depth += 1
        elif tok.type == tokenize.OP and tok.string in ")]}":
            depth -= 1
            if depth == 0:
                break
        elif tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            if tok.start[0] == key_row and tok.line[: tok.start[1]].strip():
                comments[key].append(text)
            elif depth == 1 and not tok.line[: tok.start[1]].strip():
                above.append(text)
        elif tok.type == tokenize.NL and not tok.line.strip():
            above = []  # a blank line: the comments above it are not the next key's
        elif depth == 1 and tok.type == tokenize.STRING:
            after = next(t for t in tokens[i + 1 :] if t.type not in skip)
            if after.string == ":":
                key, key_row = ast.literal_eval(tok.string), tok.start[0]
                comments[key], above = above, []
    return {key: " ".join(lines) for key, lines in comments.items() if lines}


class _Switch(argparse.Action):
    """``--key`` sets the option on, ``--no_key`` off."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, not option_string.startswith("--no_"))


def _shown(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, (list, tuple)):
        return " ".join(str(v) for v in value) or "empty"
    return str(value)


def add_conf_flags(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    owner,
    keys: Sequence[str] | None = None,
    *,
    types: dict[str, Callable[[str], Any]] | None = None,
    choices: dict[str, Sequence] | None = None,
    what: str | None = None,
    flags: dict[str, str] | None = None,
    defaults: dict[str, Any] | None = None,
) -> list[str]:
    """A flag ``--key`` for each of ``keys`` (default: all) of ``owner.default_conf``, ``owner``
    being the module or class that assigns it; returns the keys, for ``conf_from_flags``.

    The default's type is the flag's: a bool is a ``--key``/``--no_key`` pair, a list or tuple
    takes any number of values (``types`` gives their type when the default is empty), int,
    float and str one value; a None default (an option that can be off) needs its type in
    ``types`` and also takes ``none``. The help is the option's comment (``conf_comments``) and
    its default. ``choices``: the allowed values of some keys; ``flags``: the flag names of keys
    whose flag is not ``--key``; ``defaults``: the flags' defaults where they are not the
    option's (``argparse.SUPPRESS``: not given, the owner's own). A key ``default_conf`` does not
    have is merge_conf's one-line error."""
    what = what or owner.__name__.rsplit(".", 1)[-1]
    types, choices, flags, defaults = types or {}, choices or {}, flags or {}, defaults or {}
    keys = list(owner.default_conf) if keys is None else list(keys)
    merge_conf(
        owner.default_conf, dict.fromkeys([*keys, *types, *choices, *flags, *defaults]), what
    )
    comments = conf_comments(owner)
    for key in keys:
        own, kind, flag = owner.default_conf[key], types.get(key), flags.get(key, key)
        default = defaults.get(key, own)
        shown = f"--{flag}" if default is True else f"--no_{flag}" if default is False else None
        shown = f"the {what}'s" if default is argparse.SUPPRESS else shown or _shown(default)
        text = f"{comments.get(key, '')} (default: {shown})".lstrip()
        kwargs = {"default": default, "help": text.replace("%", "%%")}
        if key in choices:
            kwargs["choices"] = choices[key]
        if isinstance(own, bool):
            parser.add_argument(f"--{flag}", f"--no_{flag}", action=_Switch, **kwargs)
            continue
        if isinstance(own, (list, tuple)):
            kind = kind or (type(own[0]) if own else None)
            kwargs["nargs"] = "*"
        elif own is not None:
            kind = kind or type(own)
        elif kind is not None:
            kind = none_or(kind)
        if kind not in (int, float, str) and key not in types:
            raise TypeError(f"{what} option {key!r} (default {own!r}): give its type in types")
        parser.add_argument(f"--{flag}", type=kind, **kwargs)
    return keys


def conf_from_flags(
    args: argparse.Namespace,
    owner,
    keys: Sequence[str],
    what: str | None = None,
    flags: dict[str, str] | None = None,
) -> dict:
    """The options ``keys`` of ``owner.default_conf`` as parsed from ``add_conf_flags``'s flags
    (a list comes back as the default's list or tuple; a flag not given whose default is
    ``argparse.SUPPRESS`` is left out), checked by ``merge_conf``."""
    defaults, flags = owner.default_conf, flags or {}
    conf = {}
    for key in keys:
        if not hasattr(args, flags.get(key, key)):
            continue
        value, default = getattr(args, flags.get(key, key)), defaults.get(key)
        if isinstance(default, (list, tuple)) and value is not None:
            value = type(default)(value)
        conf[key] = value
    merge_conf(defaults, conf, what or owner.__name__.rsplit(".", 1)[-1])
    return conf

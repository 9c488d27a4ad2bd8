"""python -m recon_scripts PRESET [key=value ...]: run a benchmark preset.

A value is read as JSON when it parses (3, 0.5, true, null, ["a", "b"]), else as text; an option
whose default is a list takes items separated by spaces: sets="sacre_coeur_hloc opensfm_lund".
"""

from __future__ import annotations

import importlib
import json
import sys

from recon_scripts.bench import BASE_CONF

# preset -> the module that defines it (imported only when chosen)
PRESETS = {
    "aliked": "benchmark_aliked",
    "archive": "benchmark_scale",
    "matching": "matching.verified_pairs",
    "pairs": "benchmark_pairs",
    "pipeline": "benchmark_pipeline",
    "retrieval": "matching.retrieval",
    "scale": "benchmark_scale",
    "scale_default": "benchmark_scale",
    "scale_executors": "benchmark_scale",
}


def preset_class(name: str):
    module = importlib.import_module(f"recon_scripts.{PRESETS[name]}")
    return next(
        c for c in vars(module).values() if isinstance(c, type) and getattr(c, "name", "") == name
    )


def parse_value(text: str, default):
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = text
    if isinstance(default, list) and not isinstance(value, list):
        return [parse_value(item, None) for item in text.split()]
    return value


def usage() -> str:
    lines = [__doc__, "presets:"]
    for name in PRESETS:
        cls = preset_class(name)
        doc = cls.__doc__ or importlib.import_module(cls.__module__).__doc__
        lines.append(f"  {name:16} {doc.split(chr(10))[0]}")
    lines.append("\npython -m recon_scripts PRESET --help: its options and their defaults")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in PRESETS:
        print(usage())
        if argv and argv[0] not in ("-h", "--help"):
            print(f"\nerror: unknown preset {argv[0]!r}", file=sys.stderr)
            return 2
        return 0
    cls = preset_class(argv[0])
    if any(a in ("-h", "--help") for a in argv[1:]):
        defaults = cls({}).conf
        print(cls.__doc__ or importlib.import_module(cls.__module__).__doc__)
        print("options (key=value):\n" + "\n".join(f"  {k}={v!r}" for k, v in defaults.items()))
        return 0
    conf = {}
    for arg in argv[1:]:
        key, eq, text = arg.partition("=")
        if not eq:
            print(f"error: {arg!r} is not key=value", file=sys.stderr)
            return 2
        conf[key] = parse_value(text, {**BASE_CONF, **cls.default_conf}.get(key))
    try:
        bench = cls(conf)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    bench.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Rules by name: jsve's presets, or rule JSON files (the form `jsve fit` writes, jsve.core.rule_to_dict)."""

from __future__ import annotations


def load_rules(names: list[str] | None):
    """(name, Rule) pairs from preset names and JSON files (a file's name is its stem); None: every
    preset. Errors name the file."""
    import json
    from pathlib import Path

    from jsve.core._rules import PRESETS, preset, rule_from_dict

    pairs = []
    for name in names or list(PRESETS):
        if name in PRESETS:
            pairs.append((name, preset(name)))
            continue
        path = Path(name)
        if not path.is_file():
            raise ValueError(f"--rule {name!r} is neither a preset ({', '.join(PRESETS)}) nor a file")
        try:
            spec = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}:{err.lineno}: not valid JSON: {err.msg}") from None
        pairs.append((path.stem, rule_from_dict(spec, source=str(path))))
    return pairs

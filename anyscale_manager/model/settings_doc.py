"""The settings table of docs/configuration.md, made from model/types.py's declarations.

    python -m anyscale_manager.model.settings_doc            # print the table
    python -m anyscale_manager.model.settings_doc --write    # rewrite it in the docs

Each setting is declared once (``types.setting``: default, meaning, range, unit, live); this
prints them as one markdown table, and the test suite checks that the docs hold exactly this.
"""

import argparse
import os
import sys
from dataclasses import MISSING, fields
from typing import List

from . import types as t

SECTIONS = (('decider', t.DeciderSettings), ('monitoring', t.MonitorSettings),
            ('agent', t.AgentSettings), ('security', t.SecuritySettings),
            ('discovery', t.DiscoverySettings))
BEGIN = '<!-- settings table: made by python -m anyscale_manager.model.settings_doc --write -->'
END = '<!-- end of the settings table -->'
DOC = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                   'docs', 'configuration.md')


def _bounds(check: dict) -> str:
    if 'choices' in check:
        return ' \\| '.join(f'`{c}`' for c in check['choices'])
    if 'low' not in check:
        return ''
    low, high = check['low'], check.get('high')
    left = '(' if check.get('low_open') else '['
    text = f'{left}{low:g}, {high:g}]' if high is not None else f'{left}{low:g}, ∞)'
    return text + (f' {check["unit"]}' if check.get('unit') else '')


def _default(f) -> str:
    if f.default is not MISSING:
        value = f.default
        if isinstance(value, bool):
            return 'true' if value else 'false'
        return f'`{value}`' if isinstance(value, str) and value else (
            'none' if value == '' else f'{value:g}' if isinstance(value, float) else str(value))
    return 'none'


def table() -> str:
    rows: List[str] = ['| key | default | range | meaning |', '|---|---|---|---|']
    for section, cls in SECTIONS:
        for f in fields(cls):
            meta = f.metadata
            live = ' (taken while the decider runs)' if meta.get('live') else ''
            text = meta['help'].replace('|', '\\|')
            rows.append(f'| `{section}.{f.name}` | {_default(f)} | {_bounds(meta["check"])} | '
                        f'{text}{live} |')
    return '\n'.join(rows)


def block() -> str:
    return f'{BEGIN}\n{table()}\n{END}'


def current(path: str = DOC) -> str:
    """The block as the docs hold it now ('' when its markers are missing)."""
    with open(path, encoding='utf-8') as f:
        text = f.read()
    start, end = text.find(BEGIN), text.find(END)
    return text[start:end + len(END)] if 0 <= start < end else ''


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--write', action='store_true', help=f'rewrite the table in {DOC}')
    args = ap.parse_args(argv)
    if not args.write:
        print(table())
        return 0
    with open(DOC, encoding='utf-8') as f:
        text = f.read()
    old = current(DOC)
    if not old:
        print(f'{DOC}: the markers of the settings table are missing', file=sys.stderr)
        return 2
    with open(DOC, 'w', encoding='utf-8') as f:
        f.write(text.replace(old, block()))
    return 0


if __name__ == '__main__':
    sys.exit(main())

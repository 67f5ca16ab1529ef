"""``distilkit init``'s screens: the taps, pairs and objectives as tables, and the numbered questions asked in a
terminal (rich's prompts read through ``input()``, so a test answers on stdin)."""

from __future__ import annotations

import argparse
from typing import Any, Callable


def show(p: Any, console: Any) -> None:
    """The taps of both models, the pairs that align, and every objective: on which taps it fits, or why not."""
    from rich.table import Table

    taps = Table(title=f"taps ({p.dataset}" + (f", grid {p.grid_text})" if p.grid_text else ")"))
    for col in ("model", "tap", "kind", "channels", "size"):
        taps.add_column(col)
    for role in ("teacher", "student"):
        f = p.facts[role]
        for t in f.taps:
            kind = t.kind + (f" (made of {t.of})" if t.of else "")
            taps.add_row(f"{role} ({f.adapter})", t.tap, kind, str(t.channels if t.channels is not None else "?"),
                         t.size())
    console.print(taps)
    pairs = Table(title="pairs that align (student <- teacher)")
    for col in ("#", "student tap", "teacher tap", "kind", "how", "channels"):
        pairs.add_column(col)
    for i, pair in enumerate(p.pairs, 1):
        cs, ct = pair.student.channels, pair.teacher.channels
        pairs.add_row(str(i), pair.student.tap, pair.teacher.tap, pair.kind, pair.how,
                      f"{cs if cs is not None else '?'} <- {ct if ct is not None else '?'}")
    console.print(pairs if p.pairs else "[yellow]no pair of taps aligns[/]")
    found = Table(title="objectives (◆ chosen)")
    for col in ("objective", "weight", "taps / why not"):
        found.add_column(col, overflow="fold")
    chosen = {c.objective for c in p.chosen}
    for prop in p.found:
        where = ", ".join(f"{r}: {t}" for r, t in prop.taps.items()) + (f" (connector {prop.connector})"
                                                                          if prop.connector else "")
        mark = "◆ " if prop.objective in chosen else ""
        found.add_row(mark + prop.objective, f"{prop.weight:g}",
                      where + (f"; {prop.note}" if prop.note else "") if prop.fits else f"[dim]{prop.refused}[/]")
    console.print(found)


def ask_models(args: argparse.Namespace, console: Any,
               reasons: Callable[[str, str], dict[str, str | None] | None] | None = None) -> None:
    """The teacher, the student and the data, where the flags do not give them: numbered lists. ``reasons(teacher,
    student)``: each dataset and why it cannot serve both (None: it can); only those that can are numbered, the
    others are listed dimmed with their reason (no ``reasons``, or None from it: every dataset is numbered)."""
    from rich.markup import escape
    from rich.prompt import Prompt

    from distilkit.registry import ADAPTERS, DATASETS, load_plugins

    load_plugins()
    adapters = ADAPTERS.names()
    for role in ("teacher", "student"):
        if getattr(args, role):
            continue
        console.print(f"[bold]{role}[/]: " + "  ".join(f"{i}) {n}" for i, n in enumerate(adapters, 1)),
                      highlight=False)
        answer = Prompt.ask(f"{role} (number or name)", console=console)
        setattr(args, role, _pick(answer, adapters))
    if args.dataset is None:
        why = (reasons(args.teacher, args.student) if reasons else None) or {n: None for n in DATASETS.names()}
        names = [n for n, w in why.items() if w is None]
        if not names:
            return  # none serves both: the plan says why each does not
        console.print("[bold]data[/]: 0) the first that serves both  " +
                      "  ".join(f"{i}) {n}" for i, n in enumerate(names, 1)), highlight=False)
        for w in (w for w in why.values() if w):
            console.print(f"  [dim]not offered: {escape(w)}[/]", highlight=False)
        answer = Prompt.ask("data (number or name)", default="0", console=console)
        args.dataset = None if answer.strip() in ("", "0") else _pick(answer, names)


def _pick(answer: str, names: list[str]) -> str:
    answer = answer.strip()
    if answer.isdigit() and 1 <= int(answer) <= len(names):
        return names[int(answer) - 1]
    return answer  # a name: checked by the plan (did-you-mean on a typo)


def ask_choices(p: Any, args: argparse.Namespace, console: Any) -> None:
    """Which objectives (numbered among those that fit; Enter keeps the ◆ ones), one stage or one per objective,
    and where to write."""
    from pathlib import Path

    from rich.prompt import Confirm, Prompt

    fitting = [prop for prop in p.found if prop.fits]
    chosen = {c.objective for c in p.chosen}
    console.print("objectives that fit: " + "  ".join(
        f"{i}) {'◆' if prop.objective in chosen else ''}{prop.objective}" for i, prop in enumerate(fitting, 1)),
        highlight=False)
    answer = Prompt.ask("objectives (numbers like 1,3; Enter: the ◆ ones)", default="", console=console)
    if answer.strip():
        picked = [_pick(a, [f.objective for f in fitting]) for a in answer.replace(" ", "").split(",") if a]
        by_name = {f.objective: f for f in fitting}
        unknown = [a for a in picked if a not in by_name]
        if unknown:
            from distilkit.errors import DistilkitError

            raise DistilkitError(f"not among the objectives that fit: {', '.join(unknown)}")
        p.chosen = [by_name[a] for a in picked]
    p.each = Prompt.ask("stages", choices=["combined", "each"], default="each" if p.each else "combined",
                        console=console) == "each"
    p.baseline = Confirm.ask("a student stage without distillation (the baseline)?", default=p.baseline,
                             console=console)
    default = str(args.output or Path(f"{p.name}.yaml"))
    args.output = Path(Prompt.ask("write to", default=default, console=console))

"""``distilkit list [KIND]`` and ``distilkit schema``: the registered components (adapters, objectives, task losses,
datasets, metrics, optimizers, schedules, connectors, hooks, recorders) as tables, and the recipe's JSON schema or
Markdown reference."""

from __future__ import annotations

import argparse
from typing import Any

from distilkit.cli.base import command

EXAMPLES = {
    "list": ["distilkit list objectives", "distilkit list task_losses", "distilkit list objectives --markdown"],
    "schema": ["distilkit schema > recipe.schema.json                       # editor completion",
               "distilkit schema --markdown > docs/reference/recipe.md"],
}


def add(sub: Any) -> None:
    ls = command(sub, "list", "registered adapters, objectives, task losses, datasets, metrics, optimizers, "
                              "schedules, connectors, hooks and recorders", EXAMPLES["list"])
    ls.add_argument("kind", nargs="?", metavar="KIND", type=lambda text: text.replace("_", " "),
                    choices=["adapters", "objectives", "task losses", "datasets", "metrics", "optimizers", "schedules",
                             "connectors", "hooks", "recorders"],
                    help="one kind of component: adapters, objectives, task_losses (or 'task losses'), datasets, "
                         "metrics, optimizers, schedules, connectors, hooks, recorders (default: all)")
    ls.add_argument("--markdown", action="store_true",
                    help="objectives or datasets as Markdown (docs/reference/objectives.md, "
                         "docs/reference/datasets.md)")
    ls.set_defaults(fn=list_components)
    s = command(sub, "schema", "print the recipe JSON schema (for editor completion)", EXAMPLES["schema"])
    s.add_argument("--markdown", action="store_true", help="print the recipe reference as Markdown instead")
    s.set_defaults(fn=schema)


def list_components(args: argparse.Namespace) -> int:
    from distilkit.catalogue import cached
    from distilkit.console import make_console

    if args.markdown:
        if args.kind not in ("objectives", "datasets"):
            from distilkit.errors import DistilkitError

            raise DistilkitError("--markdown is available for `distilkit list objectives` and `list datasets`")
        print(cached(f"list-{args.kind}-markdown", lambda: _markdown(args.kind)))
        return 0
    data = cached("list", _catalogue)
    console = make_console()
    for kind, rows in data["kinds"].items():
        if args.kind and args.kind != kind.split()[0].rstrip("s") and args.kind != kind:
            continue
        if kind == "adapters" and console.width < 120:  # six columns do not read at 80: one block per adapter
            _adapter_blocks(console, rows)
            continue
        console.print(_kind_table(console, kind, rows))
    for msg in data["plugin_errors"]:
        console.print(f"[yellow]warning:[/] {msg}")
    return 0


def _markdown(kind: str) -> str:
    from distilkit.schema_doc import datasets_markdown, objectives_markdown

    return objectives_markdown() if kind == "objectives" else datasets_markdown()


def _catalogue() -> dict[str, Any]:
    """Every registered component as the cells ``distilkit list`` shows (JSON data: the catalogue keeps it)."""
    from distilkit.registry import ALL_REGISTRIES, plugin_errors

    kinds = {}
    for kind, reg in ALL_REGISTRIES.items():
        kinds[kind] = [{"name": _name_cell(reg, e), "description": e.description, "paper": e.paper,
                        "column": list_cell(kind, e),
                        **({"params": params_cell(e.obj.Params), "network": networks_cell(e.obj)}
                           if kind == "adapters" else {})} for e in reg]
    return {"kinds": kinds, "plugin_errors": list(plugin_errors)}


def _kind_table(console: Any, kind: str, rows: list[dict[str, str]]) -> Any:
    """One kind's components as a table that fits the console: every column wraps (a word longer than its column
    is folded onto the next line, never cut with an ellipsis); under 120 columns the paper is a dim line of the
    description's cell instead of a column of its own, so that the description keeps a readable width."""
    from rich.measure import Measurement
    from rich.table import Table
    from rich.text import Text

    narrow = console.width < 120
    table = Table(title=kind, title_justify="left")
    longest = max((len(r["name"]) for r in rows), default=4)
    table.add_column("name", style="bold", overflow="fold", min_width=min(longest, 22))
    table.add_column("description (paper)" if narrow else "description", overflow="fold", ratio=2)
    if not narrow:
        table.add_column("paper", overflow="fold", ratio=1)
    table.add_column(COLUMN[kind], overflow="fold", ratio=1)
    if kind == "adapters":
        table.add_column("parameters (default)", overflow="fold", ratio=1)
        table.add_column("network (by size)", overflow="fold", ratio=1)
    for r in rows:
        extra = [r["params"], r["network"]] if kind == "adapters" else []
        if narrow:
            about = Text(r["description"])
            if r["paper"] and r["paper"] != "—":
                about.append("\n" + r["paper"], style="dim")
            cells = [about]
        else:
            cells = [Text(r["description"]), Text(r["paper"])]
        table.add_row(Text(r["name"]), *cells, Text(r["column"]), *map(Text, extra))
    # as wide as its text, up to the console's width (measured to at most that; there the columns share it by ratio)
    table.expand = Measurement.get(console, console.options, table).maximum >= console.width
    return table


def _name_cell(reg: Any, e: Any) -> str:
    also = reg.aliases_of(e.name)
    return e.name + (f" (also {', '.join(also)})" if also else "")


def _adapter_blocks(console: Any, rows: list[dict[str, str]]) -> None:
    """``distilkit list adapters`` on a narrow console: each adapter's fields as a two-column table."""
    from rich.table import Table
    from rich.text import Text

    console.print("adapters")
    for r in rows:
        block = Table(title=r["name"], title_justify="left", title_style="bold", show_header=False, expand=True)
        block.add_column("field", style="dim", no_wrap=True)
        block.add_column("value", ratio=1, overflow="fold")
        for field, value in (("description", r["description"]), ("paper", r["paper"]),
                             (COLUMN["adapters"], r["column"]), ("parameters", r["params"].replace("\n", ", ")),
                             ("network", r["network"])):
            block.add_row(field, Text(value))
        console.print(block)


COLUMN = {"adapters": "taps (name: kind)", "objectives": "reads (tap kinds)", "task losses": "reads (tap kinds)",
                "datasets": "batch fields", "metrics": "scores (tap kind)", "optimizers": "—",
                "schedules": "parameters", "connectors": "—", "hooks": "parameters",
                "recorders": "—"}


def params_cell(params: Any) -> str:
    """An adapter's parameters with their defaults, one per line (docs/reference/recipe.md has their descriptions)."""
    import json

    out = []
    for name, field in params.model_fields.items():
        default = field.get_default(call_default_factory=True)
        out.append(f"{name}={json.dumps(default, default=str)}")
    return "\n".join(out) or "—"


def networks_cell(adapter: Any) -> str:
    """What each size of an adapter builds: the paper's network or a CPU stand-in."""
    networks = getattr(adapter, "NETWORKS", {})
    if "" in networks:
        return networks[""]
    return "\n".join(f"{size}: {what}" for size, what in networks.items()) or "—"


def list_cell(kind: str, entry: object) -> str:
    """What ``distilkit list`` shows of a component: an adapter's taps by name and kind, the tap kinds a term reads,
    the batch fields a dataset provides (from its default parameters), what a metric scores."""
    obj, meta = getattr(entry, "obj"), getattr(entry, "meta")
    if kind == "adapters" and getattr(obj, "TAPS", None):
        return ", ".join(f"{name}: {k}" for name, k in obj.TAPS.items())
    if kind == "datasets" and "info" in meta and "params" in meta:
        try:  # a dataset with required parameters (a root folder) still shows what its defaults give
            fields = meta["info"](meta["params"].model_construct()).fields
        except Exception:
            return "—"
        return ", ".join(sorted(fields))
    if kind in ("schedules", "hooks") and "params" in meta:
        return ", ".join(meta["params"].model_fields) or "—"
    return ", ".join(getattr(entry, "consumes")) or "—"


def schema(args: argparse.Namespace) -> int:
    from distilkit.catalogue import cached

    print(cached("schema-markdown" if args.markdown else "schema", lambda: _schema(args.markdown)))
    return 0


def _schema(markdown: bool) -> str:
    from distilkit.schema_doc import recipe_json_schema, recipe_reference_markdown

    return recipe_reference_markdown() if markdown else recipe_json_schema()

"""The recipe JSON schema and the Markdown recipe reference, both generated from :mod:`distilkit.recipe`."""

from __future__ import annotations

import json
from typing import Any

from distilkit.recipe import Recipe


def recipe_json_schema() -> str:
    """The recipe's JSON schema; a model's ``params`` follow its adapter's parameters (``if adapter == NAME then
    params: ...``), so an editor completes and checks them."""
    from distilkit.registry import ADAPTERS

    schema = Recipe.model_json_schema(by_alias=True)
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "distilkit recipe"
    defs = schema.setdefault("$defs", {})
    rules = []
    for e in ADAPTERS:
        params = e.obj.Params.model_json_schema(by_alias=True)
        for name, block in params.pop("$defs", {}).items():
            defs.setdefault(name, block)
        key = f"AdapterParams_{e.name.replace('-', '_')}"
        defs[key] = {**params, "title": f"{e.name} parameters", "additionalProperties": False}
        rules.append({"if": {"properties": {"adapter": {"const": e.name}}, "required": ["adapter"]},
                      "then": {"properties": {"params": {"$ref": f"#/$defs/{key}"}}}})
    if "ModelSpec" in defs:
        defs["ModelSpec"]["allOf"] = rules
    schema["properties"]["trackers"]["items"] = trackers_schema(defs)
    return json.dumps(schema, indent=2)


def trackers() -> list[Any]:
    """The registered trackers (hooks registered with ``tracker=True``), in registration order."""
    from distilkit.registry import HOOKS

    return [e for e in HOOKS if e.meta.get("tracker")]


def trackers_schema(defs: dict[str, Any]) -> dict[str, Any]:
    """A ``trackers`` entry: a tracker's name, or ``{NAME: {params}}`` with that tracker's parameters (each in
    ``defs`` as ``TrackerParams_<name>``)."""
    from distilkit.registry import NoParams

    names, options = [], {}
    for e in trackers():
        params = e.meta.get("params", NoParams).model_json_schema(by_alias=True)
        for name, block in params.pop("$defs", {}).items():
            defs.setdefault(name, block)
        key = f"TrackerParams_{e.name.replace('-', '_')}"
        defs[key] = {**params, "title": f"{e.name} parameters", "description": e.description,
                     "additionalProperties": False}
        names.append(e.name)
        options[e.name] = {"anyOf": [{"$ref": f"#/$defs/{key}"}, {"type": "null"}]}
    return {"anyOf": [{"type": "string", "enum": names},
                      {"type": "object", "properties": options, "additionalProperties": False,
                       "minProperties": 1, "maxProperties": 1}]}


def _type(prop: dict[str, Any]) -> str:
    if "$ref" in prop:
        return prop["$ref"].split("/")[-1]
    if "anyOf" in prop:
        return " or ".join(_type(p) for p in prop["anyOf"])
    if "enum" in prop:
        return " | ".join(json.dumps(v) for v in prop["enum"])
    if "const" in prop:
        return json.dumps(prop["const"])
    t = prop.get("type", "any")
    if t == "array":
        return f"list of {_type(prop.get('items', {}))}" if "items" in prop else "list"
    if t == "object" and "additionalProperties" in prop and isinstance(prop["additionalProperties"], dict):
        return f"mapping of {_type(prop['additionalProperties'])}"
    return t


def recipe_reference_markdown() -> str:
    """Every recipe section and field, with type, default and description (docs/reference/recipe.md)."""
    schema = Recipe.model_json_schema(by_alias=True)
    defs = schema.get("$defs", {})
    sections = [("Recipe", schema)] + sorted(defs.items())
    out = ["# Recipe reference", "",
           "Generated from the recipe schema by `distilkit schema --markdown`; a test keeps this file in sync.",
           "Unknown keys are errors. Component parameters (`params`) are checked against the named component "
           "(see `distilkit list`).", ""]
    for name, sec in sections:
        out += [f"## {name}", ""]
        if sec.get("description"):
            out += [" ".join(sec["description"].split()), ""]
        out += ["| field | type | default | description |", "|---|---|---|---|"]
        required = set(sec.get("required", []))
        for field, prop in sec.get("properties", {}).items():
            default = "*required*" if field in required else f"`{json.dumps(prop.get('default'))}`" if "default" in prop else ""
            out.append(f"| `{field}` | {_cell(_type(prop))} | {default} | {_cell(prop.get('description') or '')} |")
        out.append("")
    return "\n".join(out + OVERRIDES_MARKDOWN + trackers_markdown() + adapters_markdown())


OVERRIDES_MARKDOWN = [
    "## Overrides on the command line (`--set`)", "",
    "`distilkit run` and `distilkit validate` take `--set PATH=VALUE ...`: each sets one field of the recipe by its "
    "dotted path, the path sweep files use, before the recipe is validated (so an override is checked like the "
    "file). Values are read as YAML (`0.01` a number, `[1, 2]` a list, `true` a boolean, `{a: 1}` a mapping, "
    "anything else a string); a path goes into lists by index (`stages.s.distill.0.weight=10`). A `*` stands for "
    "every key (or list item) at its place: `--set 'stages.*.train.steps=4'` shrinks every stage at once. An "
    "override whose wildcard matches nothing, or that names a stage the recipe does not have, is an error (exit 2). "
    "Each stage's `recipe.resolved.yaml` records the values in effect.", "",
    "```bash",
    "distilkit run recipes/quickstart.yaml --set 'stages.*.train.steps=4' data.params.num_test=4",
    "distilkit validate recipes/semantickitti_scpnet.yaml --set data.params.root=/data/semantickitti",
    "```", ""]


def trackers_markdown() -> list[str]:
    """Every registered tracker (``trackers:``), what it records, what it needs, and its parameters."""
    from distilkit.registry import NoParams

    out = ["## Trackers", "",
           "`trackers: [NAME, {NAME: {param: value}}, ...]` logs every stage run to these trackers, each given once "
           "(unknown parameters are errors; a tracker's library is an optional extra, `pip install "
           "'distilkit[NAME]'`, and `validate` names what is missing: the library, MLflow's store needs, a W&B "
           "login). Each tracker's library reads its own environment variables, which win over these parameters. "
           "`every` is common to all: log training values every N steps (0: as often as `train.log_every`).", ""]
    for e in trackers():
        out += [f"### {e.name}", "", e.description + ".", ""]
        out += params_table(e.meta.get("params", NoParams))
    return out


def params_table(params: type[Any]) -> list[str]:
    """A parameter table (and one per nested parameter block) of a component's pydantic ``Params``."""
    schema = params.model_json_schema()
    defs = schema.get("$defs", {})
    out: list[str] = []
    for name, block in [("", schema)] + [(n, defs[n]) for n in sorted(defs)]:
        if name:
            out += [f"`{name}` ({' '.join((block.get('description') or '').split())})", ""]
        out += ["| parameter | type | default | description |", "|---|---|---|---|"]
        required = set(block.get("required", []))
        for field, prop in block.get("properties", {}).items():
            default = ("*required*" if field in required
                       else f"`{json.dumps(prop.get('default'))}`" if "default" in prop else "")
            out.append(f"| `{field}` | {_cell(_type(prop))} | {default} | {_cell(prop.get('description') or '')} |")
        out.append("")
    return out


def aux_only_inputs(inputs: frozenset[str]) -> list[str]:
    """The batch inputs no registered dataset provides: only a frozen auxiliary model's tap (an ``aux`` edge) can."""
    from distilkit.registry import DATASETS

    fields: set[str] = set()
    for entry in DATASETS:
        try:
            fields |= set(entry.meta["info"](entry.meta["params"].model_construct()).fields)
        except Exception:  # a dataset whose facts need parameters it has no default for
            continue
    return sorted(inputs - fields)


def adapters_markdown() -> list[str]:
    """Every registered adapter: what it is, the batch inputs it reads (those only an ``aux`` edge provides said so)
    and its parameters (``model.params``), from its ``Params``."""
    from distilkit.registry import ADAPTERS

    out = ["## Adapter parameters", "",
           "`model: {adapter: NAME, params: {...}}` takes these parameters (unknown ones are errors; "
           "`distilkit list adapters` shows the same; a field that one `size` alone reads — \"tiny:\", \"size paper:\" "
           "in its description — given with the other size is an error too).", ""]
    for e in ADAPTERS:
        inputs = e.obj.inputs(e.obj.Params.model_construct())
        aux = aux_only_inputs(inputs)
        out += [f"### {e.name}", "", e.description + ".", "", f"- **Paper:** {e.paper}",
                f"- **Reads:** {', '.join(f'`{i}`' for i in sorted(inputs)) or 'nothing'}"
                + (f"; {', '.join(f'`{i}`' for i in aux)} only from an auxiliary model: `aux: {{NAME: {{from: STAGE, "
                   f"inputs: {{TAP: {aux[0]}}}}}}}`" if aux else ""), ""]
        out += params_table(e.obj.Params)
    return out


def objectives_markdown() -> str:
    """docs/reference/objectives.md: every registered objective's paper, equation, shapes, taps, weight and
    parameters."""
    from distilkit.registry import OBJECTIVES

    out = ["# Objectives", "",
           "Generated from the objective registry by `distilkit list objectives --markdown`; a test keeps it in sync.",
           "Every objective is also a plain function in `distilkit.losses` (tested against naive float64",
           "implementations of the paper's formula). Weights are the defaults for this field when a recipe gives none.",
           "", "The last column says how each teacher tap must match its student partner's (the student role of the",
           "same suffix): channels `equal` (a student `connector` makes them so), `any` or `own` (the term projects),",
           "then `same` size, `aligned` (voxel grids in an integer ratio), `resampled` (any size: the term resizes)",
           "or `collapsed` (the teacher's voxels, height collapsed, on the student's plane); \"divides the labels'",
           "grid\": the maps are masked by the labels pooled to their size. `distilkit init` pairs taps by it, and",
           "tests/test_objective_match.py checks each against its objective.", "",
           "| name | paper | default weight | taps (role: kind) | teacher taps match the student's |",
           "|---|---|---|---|---|"]
    for e in OBJECTIVES:
        taps = ", ".join(f"{r}: {k}" + (" (optional)" if r in getattr(e.obj, "OPTIONAL", ()) else "")
                         for r, k in e.obj.CONSUMES.items())
        out.append(f"| [`{e.name}`](#{e.name}) | {e.paper} | {e.meta['default_weight']:g} | {taps} | "
                   f"{_match_text(e.obj) or '—'} |")
    out.append("")
    for e in OBJECTIVES:
        doc = " ".join((e.obj.__doc__ or "").split())
        out += [f"## {e.name}", "", e.description + ".", "", f"- **Paper:** {e.paper}",
                f"- **Equation:** `{e.meta['equation']}`", f"- **Tensors:** {e.meta['shapes']}",
                f"- **Default weight:** {e.meta['default_weight']:g}", f"- **Function:** `{e.meta['function']}`",
                *([f"- **Teacher taps:** {_match_text(e.obj)}"] if _match_text(e.obj) else []), "", doc, ""]
        props = e.obj.Params.model_json_schema().get("properties", {})
        if props:
            out += ["| parameter | default | description |", "|---|---|---|"]
            for name, prop in props.items():
                out.append(f"| `{name}` | `{json.dumps(prop.get('default'))}` | {prop.get('description', '')} |")
            out.append("")
        out += ["```yaml", "distill:", f"  - {{name: {e.name}, weight: {e.meta['default_weight']:g}}}", "```", ""]
    return "\n".join(out + choices_markdown())


def _match_text(card: Any) -> str:
    """Each teacher role's match with its default parameters (``teacher: equal · same``); one role said alone."""
    match = card.match()
    if len(match) == 1 and "teacher" in match:
        return match["teacher"].text()
    return "; ".join(f"{role}: {m.text()}" for role, m in match.items())


def choices_markdown() -> list[str]:
    """The table of every registered component's choices (:mod:`distilkit.choices`)."""
    from distilkit.choices import component_choices

    out = ["## Choices: where distilkit, the papers and the released code differ", "",
           "Every registered component lists the details where its paper and its authors' code disagree, or where",
           "neither pins one down: distilkit's default, what each source says, and the switch to the other",
           "behaviour where there is one (each also stated in the component's docstring).", "",
           "| component | topic | distilkit's default | the paper | the released code | the other way |",
           "|---|---|---|---|---|---|"]
    for kind, name, c in component_choices():
        out.append(f"| {kind} `{name}` | {_cell(c.topic)} | {_cell(c.default)} | {_cell(c.paper)} | {_cell(c.code)} | "
                   f"{_cell(c.option) or '—'} |")
    return out + [""]


def _cell(text: str) -> str:
    """Text for a Markdown table cell (its pipes escaped)."""
    return text.replace("|", "\\|")


def datasets_markdown() -> str:
    """docs/reference/datasets.md: every registered dataset's description, paper, batch fields and parameters (with
    those of nested parameter blocks such as ``camera``)."""
    from distilkit.registry import DATASETS

    out = ["# Datasets", "",
           "Generated from the dataset registry by `distilkit list datasets --markdown`; a test keeps it in sync.",
           "A recipe names one under `data.dataset` and sets its parameters under `data.params`; unknown parameters "
           "are errors.", "", "| name | description |", "|---|---|"]
    entries = list(DATASETS)
    out += [f"| [`{e.name}`](#{e.name}) | {_cell(e.description)} |" for e in entries]
    out.append("")
    for e in entries:
        params = e.meta["params"]
        doc = " ".join((params.__doc__ or "").split())
        out += [f"## {e.name}", "", e.description + ".", "", f"- **Paper:** {e.paper}", "", doc, ""]
        out += params_table(params)
    return "\n".join(out)

"""The pages' code and the documentation site.

Every fenced block of README.md and of docs/**/*.md (but the generated references, which tests/test_cli_recipe.py
and tests/test_objectives.py keep in sync with their generators) is run or checked:

* ```` ```python ````: run, the blocks of one page in order in one namespace, in a fresh interpreter (a block may
  register a component: the registries of this process stay as they were), with ``100_000`` shrunk to ``2_000``
  (same code, smaller tensors);
* ```` ```yaml ````: loads with ``yaml.safe_load``; one with ``schema_version`` is a recipe (or a sweep file) and
  goes through ``recipe_from_dict`` and ``resolve``, as ``distilkit validate --static`` checks one: no model runs;
* ```` ```bash ````: each ``distilkit …`` command parses with the CLI's parser, each ``recipes/…`` path exists, each
  ``pip install ".[x]"`` extra is in pyproject.toml and each ``pytest -m`` marker is registered.

A block right after ``<!-- no-test: why -->`` is skipped (a sketch that names what it does not define). README.md is
short (under 200 lines), its table rows and ``±`` figures stand verbatim on a page of docs/, and every relative link of
README.md and docs/**/*.md names a file. Last, the site itself builds with Sphinx without a warning (.ci/run builds it
too).
"""

from __future__ import annotations

import argparse
import contextlib
import html
import io
import json
import re
import shlex
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    from pip._vendor import tomli as tomllib

from conftest import ROOT

GENERATED = {"docs/reference/objectives.md", "docs/reference/recipe.md",  # written by distilkit itself
             "docs/reference/datasets.md"}
PAGES = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md")
                              if "_build" not in p.parts and str(p.relative_to(ROOT)) not in GENERATED)]
# a page whose recipe names the plug-in its worked example registers -> that example's folder (module tiny_adapter)
PLUGINS = {"docs/tutorials/your-own-model.md": ROOT / "docs" / "examples" / "tiny_adapter"}
# where a sweep file's relative `recipe:` is read from: the folder of the shipped sweep files
SWEEPS = ROOT / "recipes" / "sweeps"

FENCE = re.compile(r"^(?P<indent>\s*)(?P<ticks>`{3,})(?P<lang>[^`\s]*)[^`]*$")
NO_TEST = re.compile(r"^\s*<!--\s*no-test:\s*(?P<why>\S.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    page: str
    line: int  # of the opening fence, 1-based
    lang: str
    code: str
    skip: str | None  # the reason of a `<!-- no-test: ... -->` right before it

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def blocks(text: str, page: str) -> list[Block]:
    """The fenced blocks of a Markdown text, their indentation (a block in a list item) taken off."""
    lines, out, i = text.splitlines(), [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, ticks = m["indent"], m["ticks"]
        end = next((j for j in range(i + 1, len(lines)) if re.fullmatch(rf"\s*{ticks}`*\s*", lines[j])), len(lines))
        body = [line[len(indent):] if line.startswith(indent) else line.lstrip() for line in lines[i + 1:end]]
        before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        skip = NO_TEST.match(before)
        out.append(Block(page, i + 1, m["lang"].lower(), "\n".join(body) + "\n", skip["why"] if skip else None))
        i = end + 1
    return out


def page_blocks(lang: str) -> list[Block]:
    return [b for page in PAGES for b in blocks((ROOT / page).read_text(), page) if b.lang == lang]


# --- python ----------------------------------------------------------------------------------------------------

RUNNER = """
import json, sys
namespace = {"__name__": "__main__"}
for where, code in json.loads(sys.stdin.read()):
    exec(compile(code, where, "exec"), namespace)
"""


def run_python(page_blocks_: list[Block], cwd: Path) -> str | None:
    """Run a page's python blocks in a fresh interpreter; its traceback (naming ``page:line``) if one fails."""
    runnable = [(b.where, b.code.replace("100_000", "2_000")) for b in page_blocks_ if b.skip is None]
    if not runnable:
        return None
    done = subprocess.run([sys.executable, "-c", RUNNER], input=json.dumps(runnable), capture_output=True,
                          text=True, cwd=cwd, timeout=600)
    return None if done.returncode == 0 else done.stderr[-4000:]


PYTHON_PAGES = sorted({b.page for b in page_blocks("python")})


def test_the_readme_keeps_its_python_example() -> None:
    """README's `import distilkit.losses as L` block is the one way in that is code: it stays, and runs below."""
    assert any("import distilkit.losses as L" in b.code and b.skip is None
               for b in blocks((ROOT / "README.md").read_text(), "README.md") if b.lang == "python")


@pytest.mark.parametrize("page", PYTHON_PAGES)
def test_python_blocks_run(page: str, tmp_path: Path) -> None:
    """Every ```python block of the page runs (in a fresh interpreter, in an empty folder)."""
    page_python = [b for b in blocks((ROOT / page).read_text(), page) if b.lang == "python"]
    error = run_python(page_python, tmp_path)
    assert error is None, f"a python block of {page} fails:\n{error}"


# --- yaml ------------------------------------------------------------------------------------------------------

def yaml_problems(block: Block) -> list[str]:
    """The block loads as YAML; one with ``schema_version`` is a recipe (or, with ``variants``, a sweep file) that
    loads and resolves without running a model."""
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.errors import DistilkitError
    from distilkit.recipe import recipe_from_dict

    try:
        data = yaml.safe_load(block.code)
    except yaml.YAMLError as exc:
        return [f"{block.where}: not YAML: {exc}"]
    if not (isinstance(data, dict) and "schema_version" in data):
        return []  # a fragment: loading is all it can be checked for
    try:
        if "variants" in data:  # a sweep file: its variants' recipes, each resolved
            from distilkit.sweep.spec import Sweep, SweepSpec

            spec = SweepSpec.model_validate(data)
            base = yaml.safe_load((SWEEPS / spec.recipe).read_text()) if isinstance(spec.recipe, str) else spec.recipe
            recipes = list(Sweep(spec, base, block.where).recipes.values())
        else:
            recipes = [recipe_from_dict(data, block.where)]
        for recipe in recipes:
            resolve(recipe, block.where)
    except (DistilkitError, ValueError, OSError) as exc:  # ValueError: pydantic's ValidationError
        return [f"{block.where}: {type(exc).__name__}: {exc}"]
    return []


@contextlib.contextmanager
def plugin_of(page: str, monkeypatch: pytest.MonkeyPatch):
    """While a page's recipes resolve: the plug-in its worked example registers (then removed again, so this
    process's registries stay as they were)."""
    folder = PLUGINS.get(page)
    if folder is None:
        yield
        return
    from distilkit.registry import ADAPTERS

    before, imported = set(ADAPTERS.names()), "tiny_adapter" in sys.modules
    monkeypatch.syspath_prepend(str(folder))
    import tiny_adapter

    tiny_adapter.register()  # the same classes again (another test imported it): no error, nothing new
    try:
        yield
    finally:
        for name in set(ADAPTERS.names()) - before:
            ADAPTERS.remove(name)
        if not imported:
            sys.modules.pop("tiny_adapter", None)


YAML_PAGES = sorted({b.page for b in page_blocks("yaml")})


@pytest.mark.parametrize("page", YAML_PAGES)
def test_yaml_blocks_load_and_recipes_resolve(page: str, monkeypatch: pytest.MonkeyPatch) -> None:
    page_yaml = [b for b in blocks((ROOT / page).read_text(), page) if b.lang == "yaml" and b.skip is None]
    with plugin_of(page, monkeypatch):
        problems = [p for b in page_yaml for p in yaml_problems(b)]
    assert not problems, "\n".join(problems)


def test_some_yaml_blocks_are_whole_recipes() -> None:
    """The recipe check above has something to check: at least a recipe and a sweep file are shown whole."""
    whole = [yaml.safe_load(b.code) for b in page_blocks("yaml") if "schema_version" in b.code]
    assert any("stages" in d for d in whole) and any("variants" in d for d in whole)


# --- bash ------------------------------------------------------------------------------------------------------

def commands(code: str) -> list[list[str]]:
    """The simple commands of a shell block: lines joined at a trailing backslash, comments dropped, split at
    ``&&``, ``||``, ``;`` and ``|``. A line with a substitution (``$(...)``, backquotes, ``$VAR``) is left out: its
    words are not known before a shell runs it."""
    text = re.sub(r"\\\n", " ", code)
    out: list[list[str]] = []
    for line in text.splitlines():
        if re.search(r"\$[({\w]|`", line.split(" #")[0]):
            continue
        lex = shlex.shlex(line, posix=True, punctuation_chars=True)
        lex.whitespace_split = True
        words: list[str] = []
        for token in [*lex, ";"]:  # an unclosed quote raises ValueError: the test fails on it
            if token in {"&&", "||", ";", "|", "&"}:
                if words:
                    out.append(words)
                words = []
            else:
                words.append(token)
    return out


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def bash_problems(block: Block, parser: argparse.ArgumentParser, extras: set[str], markers: set[str]) -> list[str]:
    problems = []
    for path in re.findall(r"(?<![\w./-])(recipes/[\w./-]*\w)", block.code):
        if not (ROOT / path).exists():
            problems.append(f"{block.where}: {path} does not exist")
    for words in commands(block.code):
        if words[0] == "distilkit":
            err = io.StringIO()
            try:
                with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                    parser.parse_args(words[1:])
            except SystemExit as exc:
                if exc.code:
                    problems.append(f"{block.where}: `{shlex.join(words)}` does not parse: "
                                    f"{err.getvalue().strip().splitlines()[-1:]}")
        if words[:2] == ["pip", "install"]:
            for word in words[2:]:
                m = re.fullmatch(r"(?:\.|distilkit)\[([^\]]*)\]", word)
                for extra in (m[1].split(",") if m else []):
                    if extra.strip() not in extras:
                        problems.append(f"{block.where}: `{word}`: no extra {extra.strip()!r} in pyproject.toml")
        if "pytest" in words:
            args = words[words.index("pytest") + 1:]  # `python -m pytest -m X`: the first -m is python's
            for i, word in enumerate(args[:-1]):
                if word == "-m":
                    for name in set(re.findall(r"[A-Za-z_]\w*", args[i + 1])) - {"not", "and", "or"}:
                        if name not in markers:
                            problems.append(f"{block.where}: pytest marker {name!r} is not registered")
    return problems


@pytest.fixture(scope="module")
def bash_context() -> tuple[argparse.ArgumentParser, set[str], set[str]]:
    from distilkit.cli import build_parser

    config = _pyproject()
    extras = set(config["project"]["optional-dependencies"])
    markers = {re.split(r"[:(]", m)[0].strip() for m in config["tool"]["pytest"]["ini_options"]["markers"]}
    return build_parser(), extras, markers


BASH_PAGES = sorted({b.page for b in page_blocks("bash")})


@pytest.mark.parametrize("page", BASH_PAGES)
def test_bash_blocks_name_what_exists(page: str, bash_context) -> None:
    page_bash = [b for b in blocks((ROOT / page).read_text(), page) if b.lang == "bash" and b.skip is None]
    problems = [p for b in page_bash for p in bash_problems(b, *bash_context)]
    assert not problems, "\n".join(problems)


# --- the checks themselves ---------------------------------------------------------------------------------------

BROKEN = '''
```python
raise RuntimeError("a broken example")
```

<!-- no-test: a sketch -->
```python
undefined_name
```

  ```yaml
  a: [unclosed
  ```

```yaml
schema_version: 1
name: broken
data: {dataset: synthetic-lidar}
stages:
  student: {model: {adapter: no-such-adapter}}
```

```yaml
schema_version: 1
name: broken_sweep
recipe: ../quickstart.yaml
stage: no_such_stage
variants: {none: {distill: []}}
```

```bash
distilkit run recipes/no_such_recipe.yaml --no-such-option   # a comment
pip install torch && pip install -e ".[test,no-such-extra]"
python -m pytest -m "not slow and no_such_marker"
distilkit sweep recipes/sweeps/quickstart_methods.yaml --jobs 2 \\
    --no-such-flag
distilkit run "$(ls recipes/*.yaml | head -1)"
```
'''


def test_the_checks_find_a_broken_block_of_each_kind(tmp_path: Path, bash_context) -> None:
    """Each check above can fail: a made-up page with one mistake of each kind is caught, mistake by mistake, and
    the block after ``<!-- no-test: ... -->`` is skipped."""
    found = blocks(BROKEN, "broken.md")
    assert [(b.lang, b.skip) for b in found] == [("python", None), ("python", "a sketch"), ("yaml", None),
                                                 ("yaml", None), ("yaml", None), ("bash", None)]
    python, yamls, bash = found[:2], found[2:5], found[5]
    assert "a broken example" in (run_python(python, tmp_path) or "")
    assert run_python(python[1:], tmp_path) is None  # the skipped block is never run

    not_yaml, bad_recipe, bad_sweep = (yaml_problems(b) for b in yamls)
    assert len(not_yaml) == 1 and "not YAML" in not_yaml[0] and yamls[0].code.startswith("a: [")
    assert len(bad_recipe) == 1 and "no-such-adapter" in bad_recipe[0]
    assert len(bad_sweep) == 1 and "no_such_stage" in bad_sweep[0]

    problems = bash_problems(bash, *bash_context)
    assert any("recipes/no_such_recipe.yaml does not exist" in p for p in problems)
    assert any("distilkit run recipes/no_such_recipe.yaml --no-such-option" in p and "does not parse" in p
               for p in problems)
    assert any("no extra 'no-such-extra'" in p for p in problems)
    assert not any("'test'" in p for p in problems)
    assert any("marker 'no_such_marker'" in p for p in problems) and not any("'slow'" in p for p in problems)
    assert any("--no-such-flag" in p for p in problems)  # the continued line is one command
    assert len(problems) == 5, problems  # the substituted line is left out
    assert commands("a && b | c; d  # e && f")[:4] == [["a"], ["b"], ["c"], ["d"]]


# --- the short README and the links -----------------------------------------------------------------------------

README_MAX_LINES = 200  # the README is a summary; the site holds the rest (design61 B6)
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")  # [text](target), ![alt](target)
INLINE_CODE = re.compile(r"``.+?``|`[^`]+`", re.S)  # a code span may run over a line break
NUMBER = r"[+−-]?\d(?:[\d,.]*\d)?"  # 1,114 or −0.15; a full stop after it ends a sentence
PLUSMINUS = re.compile(rf"{NUMBER}\s*±\s*{NUMBER}")  # 38.98 ± 1.21, +2.48 ± 1.03
INTERVAL = re.compile(rf"\[{NUMBER}, {NUMBER}\]")  # [+1.41, +3.56]
LINK_PAGES = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md")
                                   if "_build" not in p.parts)]


def prose(text: str) -> str:
    """The text outside fenced blocks and code spans, where brackets and parentheses are code, not links."""
    out, ticks = [], None
    for line in text.splitlines():
        m = FENCE.match(line)
        if ticks is None and m:
            ticks = m["ticks"]
        elif ticks is not None:
            if re.fullmatch(rf"\s*{ticks}`*\s*", line):
                ticks = None
        else:
            out.append(line)
    return INLINE_CODE.sub("", "\n".join(out))


def broken_links(text: str, page: Path) -> list[str]:
    """The relative links of a page that name no file (a folder is not a file); the anchor after ``#`` is left to
    the site's build, which checks it (myst.xref_missing), and ``http:``/``mailto:`` links to the world."""
    problems = []
    for target in LINK.findall(prose(text)):
        if target.startswith("#") or re.match(r"[A-Za-z][\w+.-]*:", target):
            continue
        if not (page.parent / target.split("#")[0]).is_file():
            problems.append(f"{page.relative_to(ROOT) if page.is_relative_to(ROOT) else page}: ({target}) "
                            "names no file")
    return problems


def figures(text: str) -> list[str]:
    """What a reader compares between the README and the site: every table row and every ``±`` figure and interval."""
    rows = [line.strip() for line in text.splitlines() if line.lstrip().startswith("|")]
    return rows + PLUSMINUS.findall(text) + INTERVAL.findall(text)


def figures_not_on_the_site(readme: str, site_pages: list[str]) -> list[str]:
    return [f for f in figures(readme) if not any(f in page for page in site_pages)]


def too_long(readme: str) -> str | None:
    n = len(readme.splitlines())
    return None if n < README_MAX_LINES else f"README.md has {n} lines: at most {README_MAX_LINES - 1}; move the " \
                                             "rest to a page of docs/"


def test_the_readme_is_short() -> None:
    problem = too_long((ROOT / "README.md").read_text())
    assert problem is None, problem


@pytest.mark.parametrize("page", LINK_PAGES)
def test_every_relative_link_names_a_file(page: str) -> None:
    problems = broken_links((ROOT / page).read_text(), ROOT / page)
    assert not problems, "\n".join(problems)


def test_the_readmes_figures_are_the_sites() -> None:
    """Every table row and every ``±`` figure or interval of README.md stands, verbatim, on a page of the site: the
    README copies the site's figures and never has figures of its own."""
    readme = (ROOT / "README.md").read_text()
    assert any(line.startswith("|") for line in figures(readme)) and PLUSMINUS.search(readme)  # something to compare
    site = [p.read_text() for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts]
    missing = figures_not_on_the_site(readme, site)
    assert not missing, "in README.md but on no page of docs/:\n" + "\n".join(missing)


def test_the_readme_checks_find_what_they_look_for(tmp_path: Path) -> None:
    """Each check above can fail: a made-up page's broken links are found (a folder is no file; code is not a
    link), a README of 200 lines is too long, and a figure that differs from the site's is named."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "page.md").write_text("# a page\n")
    page = tmp_path / "README.md"
    text = ("[fine](docs/page.md#a-page) [web](https://example.org) [here](#top) ![img](docs/missing.png)\n"
            "[gone](docs/gone.md) [a folder](docs/) `[code](not/a/link.md)`\n"
            "```python\nx = d[k](y)  # [code](not/a/link.md)\n```\n")
    problems = broken_links(text, page)
    assert len(problems) == 3, problems
    assert all(any(f"({t})" in p for p in problems) for t in ("docs/missing.png", "docs/gone.md", "docs/"))

    assert too_long("line\n" * (README_MAX_LINES - 1)) is None
    assert "200 lines" in (too_long("line\n" * README_MAX_LINES) or "")

    site = ["| method | Δ |\n|---|---|\n| DIST ×3 | +2.48 ± 1.03 |\n", "DIST: [+1.41, +3.56]"]
    same = "| method | Δ |\n|---|---|\n| DIST ×3 | +2.48 ± 1.03 |\n\nIts interval [+1.41, +3.56]."
    assert figures_not_on_the_site(same, site) == []
    changed = same.replace("+2.48 ± 1.03 |", "+2.49 ± 1.03 |").replace("+3.56]", "+3.57]") + " Also 1.2 ± 0.3."
    assert figures_not_on_the_site(changed, site) == ["| DIST ×3 | +2.49 ± 1.03 |", "+2.49 ± 1.03", "1.2 ± 0.3",
                                                      "[+1.41, +3.57]"]


# --- the site --------------------------------------------------------------------------------------------------

def test_the_site_builds_without_a_warning(tmp_path: Path) -> None:
    """``python -m sphinx -b html -W --keep-going docs SITE``, as .ci/run builds it: a warning (a broken link or
    anchor, a docstring that is not reST, a module the API pages cannot import) fails; the API pages hold the
    documented functions."""
    for module in ("sphinx", "myst_parser", "furo", "sphinxarg"):
        pytest.importorskip(module, reason='the docs extra: pip install -e ".[docs]"')
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "sphinx", "-b", "html", "-W", "--keep-going", "-q", "-E",
                           str(ROOT / "docs"), str(site)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-6000:]
    assert not done.stderr.strip(), done.stderr[-6000:]
    losses = (site / "reference" / "api" / "losses.html").read_text()
    assert 'id="distilkit.losses.dskd"' in losses and 'id="distilkit.losses.kd"' in losses
    contracts = (site / "reference" / "api" / "contracts.html").read_text()
    assert 'id="distilkit.adapter.Adapter"' in contracts and 'id="distilkit.registry.NoParams"' in contracts
    assert (site / "getting-started.html").is_file() and (site / "tutorials" / "your-own-model.html").is_file()
    cli = (site / "reference" / "cli.html").read_text()
    from distilkit.cli import build_parser

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert [c for c in commands if f'id="distilkit-{c}"' not in cli] == []
    # the examples are a literal block, one line each, with plain quotes and dashes (they paste into a shell)
    assert "distilkit run recipes/quickstart.yaml --set 'stages.*.train.steps=4'" in html.unescape(
        re.sub(r"<[^>]+>", "", cli))


def test_the_cli_page_shows_each_commands_text_after_its_options_as_written() -> None:
    """docs/_cli.py: the parser of reference/cli.md is distilkit's, every epilog made a literal block whose lines
    are the terminal's."""
    sys.path.insert(0, str(ROOT / "docs"))
    try:
        import _cli
    finally:
        sys.path.remove(str(ROOT / "docs"))
    from distilkit.cli import build_parser

    def epilogs(parser: argparse.ArgumentParser) -> dict[str, str]:
        subs = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        out = {parser.prog: parser.epilog or ""}
        for child in (subs.choices.values() if subs else []):
            out.update(epilogs(child))
        return out

    ours, theirs = epilogs(build_parser()), epilogs(_cli.parser())
    assert ours.keys() == theirs.keys() and "distilkit data rectify" in ours
    for prog, text in ours.items():
        if text:
            assert theirs[prog].startswith("::\n\n") and textwrap.dedent(theirs[prog][4:]) == textwrap.dedent(text)

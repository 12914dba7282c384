"""The documentation runs: README's quick start and the code of the getting-started page
and the guides execute as pasted, the home page shows the quick start's real output, and
every public name has a page in the API reference.

A guide whose code loads a benchmark (`oj.datasets.load_emps()`, ...) runs in its own test,
which skips, naming the files, where they are not found (they are not in the repository)."""

import contextlib
import importlib.util
import io
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import benchmark_or_skip

import oneshot_jax as oj

ROOT = Path(__file__).resolve().parent.parent
GUIDES = [
    "docs/getting-started.md",
    "docs/guides/solvers.md",
    "docs/guides/constraints.md",
    "docs/guides/fixed-and-x0.md",
    "docs/guides/data.md",
    "docs/guides/uncertainty.md",
    "docs/guides/parallel.md",
    "docs/guides/real-data.md",
    "docs/guides/hybrid.md",
    "docs/guides/operating-points.md",
]


def _blocks(path):
    text = (ROOT / path).read_text()
    return re.findall(r"```python\n(.*?)```", text, re.S)


def _loaders(path):
    """The dataset loaders a page's code calls without a path (the default search)."""
    return sorted(set(re.findall(r"datasets\.(load_\w+)\(\s*\)", "\n".join(_blocks(path)))))


DATA_GUIDES = [g for g in GUIDES if _loaders(g)]


def _run(paths, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__main__"}
    for path in paths:
        blocks = _blocks(path)
        assert blocks, f"{path} has no python code"
        for block in blocks:
            exec(compile(block, str(ROOT / path), "exec"), namespace)
    return namespace


def _generate():
    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_quick_start_runs_and_the_home_page_shows_its_output(tmp_path, monkeypatch):
    """README's quick start is the home page's (docs/snippets/quickstart.py), and the
    output the home page shows (docs/snippets/quickstart.txt, written by
    `python docs/generate.py`) is what it prints, up to the wall time and the last
    digits."""
    generate = _generate()
    (readme_code,) = _blocks("README.md")
    assert readme_code == generate.QUICK_START.read_text(), (
        "README's quick start differs from docs/snippets/quickstart.py; keep them the same"
    )
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        ns = _run(["README.md"], tmp_path, monkeypatch)
    assert ns["result"].success
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150
    stored = generate.QUICK_START_OUTPUT.read_text()
    assert generate.same_output(out.getvalue(), stored), (
        "the quick start's output changed; run `python docs/generate.py` and commit "
        f"docs/snippets/quickstart.txt.\nNow:\n{out.getvalue()}\nStored:\n{stored}"
    )
    home = (ROOT / "docs" / "index.md").read_text()
    assert '--8<-- "quickstart.py"' in home and '--8<-- "quickstart.txt"' in home


# (the pages show outputs generated at XLA's default optimisation level: conftest.py)
@pytest.mark.default_optimisation
@pytest.mark.parametrize("page", sorted(_generate().PAGE_OUTPUTS))
def test_pages_show_what_their_code_prints(page, tmp_path, monkeypatch):
    """A page that prints a result shows the output of its first code block, generated
    by `python docs/generate.py` and included from docs/snippets/."""
    generate = _generate()
    snippet = generate.PAGE_OUTPUTS[page]
    assert f'```text\n--8<-- "{snippet.name}"\n```' in (ROOT / page).read_text()
    monkeypatch.chdir(tmp_path)
    now, stored = generate.run_first_block(page), snippet.read_text()
    assert generate.same_output(now, stored), (
        f"what {page} prints changed; run `python docs/generate.py` and commit "
        f"docs/snippets/{snippet.name}.\nNow:\n{now}\nStored:\n{stored}"
    )


# The hybrid guide is the longest: run in a test of its own (in parallel with the others
# under pytest-xdist).
LONG_GUIDES = ["docs/guides/hybrid.md"]


def test_getting_started_and_guides_run(tmp_path, monkeypatch):
    pages = [g for g in GUIDES if g not in DATA_GUIDES and g not in LONG_GUIDES]
    ns = _run(pages, tmp_path, monkeypatch)
    assert ns["result"].success and ns["again"].loss == ns["result"].loss


@pytest.mark.parametrize("path", [g for g in LONG_GUIDES if g not in DATA_GUIDES])
def test_long_guides_run(path, tmp_path, monkeypatch):
    """A long guide, on its own: its code imports and defines what it uses."""
    _run([path], tmp_path, monkeypatch)


def test_minima_guide_runs(tmp_path, monkeypatch):
    """docs/guides/minima.md runs on its own, and its asserts pin the numbers its text
    quotes (the bad minimum, the windowed fit, the continuation, the stability value)."""
    _run(["docs/guides/minima.md"], tmp_path, monkeypatch)


@pytest.mark.parametrize("path", DATA_GUIDES)
def test_guides_on_the_benchmark_files_run(path, tmp_path, monkeypatch):
    """The guides that load a benchmark, each on its own; a skip names the files when
    they are not found."""
    for name in _loaders(path):
        benchmark_or_skip(getattr(oj.datasets, name))
    ns = _run([path], tmp_path, monkeypatch)
    if path == "docs/guides/real-data.md":
        _check_real_data_prose(ns)


def _check_real_data_prose(ns):
    """The numbers the real-data guide's prose quotes are those its code computes: the
    protocol FIT of the basic tanks model, and how the residual's cross-correlation with
    the pump voltage sits against Ljung's band and the white one (`plot.resid`'s)."""
    text = (ROOT / "docs" / "guides" / "real-data.md").read_text()
    test, prediction = ns["test"], ns["prediction"]
    fit = oj.metrics.benchmark_scores(test.y[:, None], prediction.z, test.n).fit_percent[0]
    assert f"FIT {fit:.1f} %" in text and f"({fit:.2f} %, the" in text, fit
    rc = oj.metrics.residual_correlations(ns["tanks_fit"].residuals, ns["train"].u[:, None])
    # Ljung's band of a coloured residual and input: its widening, and no lag outside it
    widening = rc.cross_bound[0, 0] / rc.bound[0]
    assert f"here {widening:.1f} times the white band" in text, widening
    assert not np.any(np.abs(rc.cross[:, 0, 0]) > rc.cross_bound[0, 0]) and rc.independent[0]
    assert "stays inside it at every lag" in text
    # ... while lags of about 25 would leave the white band
    white = rc.lags[(np.abs(rc.cross[:, 0, 0]) > rc.bound[0]) & (rc.lags >= 0)]
    assert white.size and abs(np.median(white) - 25) <= 3, white


def test_non_uniform_guide_runs(tmp_path, monkeypatch):
    """The CSTR of the non-uniform observations guide: the aggregated fit recovers the
    parameters within its intervals, the midpoint fit is further off (its bias)."""
    ns = _run(["docs/guides/non-uniform.md"], tmp_path, monkeypatch)
    cstr, result, midpoint = ns["cstr"], ns["result"], ns["midpoint"]
    assert result.success and midpoint.success
    lo, hi = result.ci95
    for name, true in cstr.THETA_TRUE.items():
        assert lo[name] <= true <= hi[name]
        assert abs(midpoint.theta[name] - true) > abs(result.theta[name] - true)


def _public_names():
    names = set()
    for name in dir(oj):
        if name.startswith("_"):
            continue
        obj = getattr(oj, name)
        if getattr(obj, "__module__", "").startswith("oneshot_jax") or callable(obj):
            names.add(name)
    return names


@pytest.mark.parametrize("name", sorted(_public_names()))
def test_every_public_name_is_in_the_api_reference(name):
    api = "\n".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md"))
    module = getattr(oj, name)
    if isinstance(module, type(oj)):  # a public module: its page documents it
        assert f"::: oneshot_jax.{name}" in api, name
    else:
        assert f"::: oneshot_jax.{name}\n" in api, name


def test_the_site_renders_without_a_network():
    """The site's scripts and styles are its own (MathJax vendored), and the theme loads no
    web fonts: Material's default fetched Roboto from Google Fonts on every page."""
    import yaml

    class Loader(yaml.SafeLoader):  # (mkdocs' own tags, `!relative`, read as plain text)
        pass

    Loader.add_multi_constructor("!", lambda loader, tag, node: None)
    conf = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=Loader)
    assert conf["theme"].get("font") is False
    for entry in conf.get("extra_javascript", []) + conf.get("extra_css", []):
        assert "://" not in str(entry), entry
        assert (ROOT / "docs" / str(entry)).is_file(), entry


def test_every_page_that_fits_runs_in_float64_or_continues_one_that_does():
    # (the real-data guide's code, pasted alone, fitted in float32: another optimum and
    # stop than the page shows; the tests run with x64 on, so running it could not tell)
    pages = sorted((ROOT / "docs").rglob("*.md"))
    checked = 0
    for page in pages:
        path = str(page.relative_to(ROOT))
        code = "\n".join(_blocks(path))
        if not re.search(r"\boj\.fit\w*\(", code):
            continue
        checked += 1
        head = page.read_text()[:600]
        continues = "continues the [getting-started](../getting-started.md) page" in head
        first = _blocks(path)[0]
        assert continues or 'jax.config.update("jax_enable_x64", True)' in first, (
            f"{path} fits without enabling float64 in its first code block and does not say "
            "it continues the getting-started page"
        )
    assert checked >= 8

"""The documentation: the site builds with `mkdocs build --strict`, every relative link of the README and the docs
names a file of the repository, nothing refers to documents outside it, and every results table is what its
sources under results/ give (python -m experiments.results_tables --check)."""
from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from experiments import results_tables as RT

ROOT = Path(__file__).resolve().parents[1]

# spelled in two parts, so that this file does not contain what it looks for
FORBIDDEN = ["DESIGN" + ".md", ".." + "/shared"]
SCANNED = ["README.md", "CHANGELOG.md", "mkdocs.yml", "docs", "lnf", "conf", "tests", "examples", "experiments",
           "results"]
TEXT_SUFFIXES = {".md", ".py", ".yaml", ".yml", ".toml", ".txt", ".cfg", ".json", ".csv", ".ini", ".sh", ""}
LINK = re.compile(r"!?\[(?P<text>[^\]\n]*)\]\((?P<target>[^)\s]+)(?:\s+\"[^\"]*\")?\)")
HTML_LINK = re.compile(r"<(?:a|img)\b[^>]*?\b(?:href|src)=\"(?P<target>[^\"]+)\"")


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]


def links(path: Path) -> list[tuple[int, str]]:
    """(line, target) of every Markdown and HTML link and image outside code blocks and inline code."""
    out, fenced = [], False
    for number, line in enumerate(path.read_text().split("\n"), 1):
        if re.match(r"^\s*(```|~~~)", line):
            fenced = not fenced
            continue
        if fenced:
            continue
        line = re.sub(r"`[^`]*`", "", line)
        out += [(number, m.group("target")) for m in LINK.finditer(line)]
        out += [(number, m.group("target")) for m in HTML_LINK.finditer(line)]
    return out


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site, built once for the tests of this file that read it (one xdist_group keeps them on one worker):
    (the finished `mkdocs build --strict`, the site folder, the build's seconds)."""
    out = tmp_path_factory.mktemp("docs") / "site"
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    return proc, out, time.perf_counter() - start


def _built(site) -> Path:
    proc, out, _ = site
    assert proc.returncode == 0, ("mkdocs build --strict failed (pip install -e '.[dev]' installs mkdocs and its "
                                  "plugins):\n" + proc.stderr[-5000:])
    return out


@pytest.mark.xdist_group("docs_site")
def test_site_builds_in_strict_mode(site):
    seconds = site[2]
    site = _built(site)
    for page in ["index.html", "method.html", "configuration.html", "own_system.html", "data_format.html",
                 "scaling.html", "results.html", "choices.html", "api.html", "changelog.html"]:
        assert (site / page).is_file(), page
    api = (site / "api.html").read_text()
    for name in ["lnf.load", "lnf.scenes.Scene", "lnf.scenes.check.check_scene", "lnf.trajectories.write_dataset",
                 "lnf.mesh_io.read_mesh_series", "lnf.integrators.get_integrator", "lnf.metrics"]:
        assert name in api, f"the API reference has no {name}"
    assert "Keep a Changelog" in (site / "changelog.html").read_text()
    assert seconds < 120


# the modules of the model itself, which the README sends readers to, with one member each that the page must show
MODEL_MODULES = {"lnf.siren": "lnf.siren.ModulatedSiren", "lnf.reduction": "lnf.reduction.reduce",
                 "lnf.dynamics": "lnf.dynamics.ReducedDynamics", "lnf.tabulated": "lnf.tabulated.TabulatedDynamics"}
# a Sphinx role as Markdown leaves it: `:meth:` before the rendered name (docs/_hooks/sphinx_roles.py rewrites them)
RAW_ROLE = re.compile(r":(?:py:)?(?:meth|class|func|attr|mod|data|obj|exc):(?:<code>|`)")


@pytest.mark.xdist_group("docs_site")
def test_the_api_reference_covers_the_model_renders_roles_and_shows_types(site):
    api = (_built(site) / "api.html").read_text()
    for module, member in MODEL_MODULES.items():
        assert f'id="{module}"' in api, f"the API reference leaves out {module}"
        assert f'id="{member}"' in api, f"the API reference has no {member}"
    raw = sorted({m.group(0) for m in RAW_ROLE.finditer(api)})
    assert not raw, f"the API reference prints raw Sphinx roles: {raw}"
    assert "<autoref" not in api, "a cross-reference of a docstring was left unprocessed"
    assert 'href="#lnf.reduction.reduce"' in api, "the roles of the docstrings do not link to the objects they name"
    start = api.index('id="lnf.reduction.reduce"')
    signature = api[api.index('<div class="doc-signature', start):]
    signature = re.sub(r"<[^>]+>", "", signature[:signature.index("</pre>")]).replace("&gt;", ">")
    assert "steps: int" in signature and "-> Tensor" in signature, f"the signature shows no types: {signature}"


def test_the_docs_write_no_latex_markup():
    """The site renders no TeX: exponents and indices are Unicode (ℓʳ, q̃⁽⁰⁾, ∛2) or <sup>/<sub>, never ^{…} or _{…}."""
    hits = []
    for path in markdown_files()[2:]:
        fenced = False
        for number, line in enumerate(path.read_text().split("\n"), 1):
            if re.match(r"^\s*(```|~~~)", line):
                fenced = not fenced
            elif not fenced and re.search(r"[\^_]\{", re.sub(r"`[^`]*`", "", line)):
                hits.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not hits, "TeX markup that the site prints as it stands:\n" + "\n".join(hits)


def test_every_relative_link_resolves_inside_the_repository():
    bad = []
    for path in markdown_files():
        for number, target in links(path):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                continue  # a URL (checked below) or an anchor of the page (checked by mkdocs for docs/)
            relative = target.split("#", 1)[0]
            resolved = (path.parent / relative).resolve()
            where = f"{path.relative_to(ROOT)}:{number}: {target}"
            if target.startswith("/") or not resolved.is_relative_to(ROOT):
                bad.append(f"{where} (leaves the repository)")
            elif not resolved.exists():
                bad.append(f"{where} (no such file)")
    assert not bad, "broken links:\n" + "\n".join(bad)


def test_the_docs_link_to_nothing_outside_the_repository():
    external = [f"{p.relative_to(ROOT)}:{n}: {t}" for p in markdown_files() for n, t in links(p)
                if re.match(r"^(https?|ftp):", t)]
    assert not external, "the project stands on its own; links outside it:\n" + "\n".join(external)


def test_no_file_refers_to_documents_outside_the_repository():
    hits = []
    for entry in SCANNED:
        base = ROOT / entry
        files = [base] if base.is_file() else [p for p in base.rglob("*") if p.is_file()]
        for path in files:
            if "__pycache__" in path.parts or path.suffix not in TEXT_SUFFIXES:
                continue
            try:
                text = path.read_text()
            except UnicodeDecodeError:
                continue
            for number, line in enumerate(text.split("\n"), 1):
                hits += [f"{path.relative_to(ROOT)}:{number}: {line.strip()[:120]}" for word in FORBIDDEN if word in line]
    assert not hits, "references to documents outside the repository (point to docs/method.md instead):\n" + "\n".join(hits)


def test_readme_keeps_its_three_commands_first_and_stays_short():
    lines = (ROOT / "README.md").read_text().split("\n")
    assert lines[2] == "```bash" and lines[6] == "```"
    assert lines[3].startswith('pip install "torch==2.13.0" -e ".[dev]"')
    assert lines[4].startswith("python -m lnf.train +experiment=pendulum")
    assert lines[5].startswith("python -m pytest -q")
    assert len(lines) <= 201, f"README.md has {len(lines)} lines; it is a front door (≤ 200), the docs hold the rest"


def test_results_tables_match_their_sources():
    proc = subprocess.run([sys.executable, "-m", "experiments.results_tables", "--check"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_every_results_source_has_its_provenance():
    folders = sorted(p for p in RT.RESULTS.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert folders
    for folder in folders:
        if RT.SPECS.get(folder.name) is not None and RT.SPECS[folder.name].kind == "cells":
            assert (folder / "cells.json").is_file(), f"{folder.name}: a table of quoted cells needs its cells.json"
            continue  # its provenance is that of the tables it quotes
        prov = json.loads((folder / "provenance.json").read_text())
        for key in ("machine", "date", "command"):
            assert prov.get(key), f"{folder.name}: provenance.json has no {key}"
        assert isinstance(prov.get("transcribed_from_docs"), bool), folder.name
        if prov["transcribed_from_docs"]:
            rows = list(csv.reader(open(folder / "table.csv", newline="")))
            assert len(rows) >= 2 and all(len(r) == len(rows[0]) for r in rows), f"{folder.name}: ragged table.csv"


def test_a_changed_cell_is_found_and_rebuilt():
    text = (ROOT / "README.md").read_text()
    assert "<!-- results:summary -->" in text
    header, rows, _, _ = RT.table_of("summary")
    cell = rows[0][1]
    drifted = text.replace(f"| {cell} |", "| 0.5 · 0.5 · 0.5 |", 1)
    assert drifted != text and RT.rebuild(drifted, "README.md") == text


def test_a_marker_without_sources_or_end_is_an_error():
    with pytest.raises(RT.TableError, match="no such folder"):
        RT.rebuild("<!-- results:no-such-table -->\n<!-- /results:no-such-table -->\n", "x.md")
    with pytest.raises(RT.TableError, match="no closing"):
        RT.rebuild("<!-- results:summary -->\n| a |\n", "x.md")


def test_collect_copies_a_study_and_the_table_follows_its_summary(tmp_path, monkeypatch):
    study = tmp_path / "outputs" / "studies" / "stability"
    (study / "train_lnf" / "0").mkdir(parents=True)
    (study / "stability.csv").write_text("sweep,job,method\ntrain_lnf,0,lnf\n")
    (study / "summary.md").write_text(
        "# Stability study (pendulum, reduced settings)\n\nMachine: x86_64, 2 cores visible, torch 2.13.0+cpu, "
        "2 threads. Command: `python experiments/stability.py`.\n\n| method | energy drift 20× |\n|---|---|\n"
        "| LNF (ours) | 2.65e-05 |\n")
    (study / "train_lnf" / "0" / "run.json").write_text(json.dumps({"git_commit": "0123456789abcdef", "git_dirty": False}))
    monkeypatch.setattr(RT, "RESULTS", tmp_path / "results")
    out = RT.collect("stability-pendulum", study)
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["transcribed_from_docs"] is False and prov["commit"] == "0123456"
    assert prov["command"] == "python experiments/stability.py" and prov["machine"].startswith("x86_64, 2 cores")
    assert (out / "stability.csv").is_file()
    lines = RT.render("stability-pendulum")
    assert lines[:3] == ["| method | energy drift 20× |", "|---|---|", "| LNF (ours) | 2.65e-05 |"]
    assert "transcribed" not in lines[-1] and "at commit 0123456" in lines[-1]


def test_collect_of_a_pareto_study_records_the_body_dimension_its_summary_states(tmp_path, monkeypatch):
    """The soft body's 32 × 10 × 6 grid: the dimension comes from the study's summary, not from its point count."""
    study = tmp_path / "outputs" / "studies" / "pareto"
    study.mkdir(parents=True)
    (study / "pareto.csv").write_text("sweep,job,method\nwidth,0,lnf\n")
    (study / "summary.md").write_text("# Pareto study (soft_body, reduced settings)\n\nMachine: x86_64. Command: "
                                      "`python experiments/pareto.py --scene soft_body`. Body dimension: 3.\n")
    monkeypatch.setattr(RT, "RESULTS", tmp_path / "results")
    out = RT.collect("pareto-pendulum", study)
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["body_dim"] == 3 and prov["command"] == "python experiments/pareto.py --scene soft_body"
    (study / "summary.md").write_text("# Pareto study\n\nMachine: x86_64. Command: `python experiments/pareto.py`.\n")
    with pytest.raises(RT.TableError, match="Body dimension"):
        RT.collect("pareto-pendulum", study)


def test_collect_reads_a_command_of_either_spelling_and_a_rerun_is_spelled_the_new_way(tmp_path, monkeypatch):
    """Runs before the studies became the package `experiments` recorded `python experiments/<study>.py`; newer ones
    record `python -m experiments.<study>` (its dots end no field of the summary line). Both are kept as recorded;
    the rerun a transcribed table suggests is spelled the new way."""
    study = tmp_path / "outputs" / "studies" / "pareto"
    study.mkdir(parents=True)
    (study / "pareto.csv").write_text("sweep,job,method\nwidth,0,lnf\n")
    monkeypatch.setattr(RT, "RESULTS", tmp_path / "results")
    for command in ("python -m experiments.pareto --scene soft_body", "python experiments/pareto.py --scene soft_body"):
        (study / "summary.md").write_text(f"# Pareto\n\nMachine: x86_64. Command: `{command}`. Body dimension: 3.\n")
        prov = json.loads((RT.collect("pareto-pendulum", study) / "provenance.json").read_text())
        assert prov["command"] == command and prov["body_dim"] == 3
        transcribed = {**prov, "transcribed_from_docs": True}
        line = RT.provenance_line("pareto-pendulum", transcribed, RT.SPECS["pareto-pendulum"])
        assert f"by `{command}`" in line and "rerun `python -m experiments.pareto --scene soft_body`" in line
    assert RT.rerun_command("PYTHONPATH=examples python experiments/stability.py --config-dir examples/conf") == \
        "PYTHONPATH=examples python -m experiments.stability --config-dir examples/conf"
    assert RT.rerun_command("python -m lnf.train +experiment=pendulum") == "python -m lnf.train +experiment=pendulum"


def test_a_table_of_a_nested_results_file_reads_its_keys_joined_by_slashes(tmp_path, monkeypatch):
    """experiments/scenes.py writes results.json with nested objects ("damped": {...}): a row names them a/b."""
    run = tmp_path / "outputs" / "scenes" / "soft_body"
    run.mkdir(parents=True)
    (run / "results.json").write_text(json.dumps({"speedup": 536.2, "ours": {"field_rel_l2/in_horizon/median": 0.021},
                                                  "damped": {"damping_per_second": 0.5}}))
    monkeypatch.setattr(RT, "RESULTS", tmp_path / "results")
    monkeypatch.setitem(RT.SPECS, "x_scenes", RT.Spec("metrics", "python experiments/scenes.py", file="results.json",
                                                      metrics=(("speed-up", "speedup"),
                                                               ("error · α", "ours/field_rel_l2/in_horizon/median|"
                                                                             "damped/damping_per_second"),
                                                               ("absent", "nothing/here"))))
    out = RT.collect("x_scenes", run)
    assert (out / "results.json").is_file()
    lines = RT.render("x_scenes")
    assert lines[:4] == ["| metric | value |", "|---|---|", "| speed-up | 536 |", "| error · α | 0.021 · 0.5 |"]


def test_a_stacked_table_takes_the_marked_row_of_each_study_and_their_provenance(tmp_path, monkeypatch):
    """roofline-defaults: the default configuration's row of each scene's roofline.csv, one table."""
    results = tmp_path / "results"
    for scene, ms, commit in [("a", 0.0279, "0123456"), ("b", 0.0457, "0123456")]:
        folder = results / f"roofline-{scene}"
        folder.mkdir(parents=True)
        (folder / "roofline.csv").write_text(f"method,width,seconds,ratio,default\nlnf,64,0.5,9.0,False\n"
                                             f"lnf,256,{ms},2.6,True\n")
        (folder / "provenance.json").write_text(json.dumps({"machine": "m", "date": "2026-12-03", "commit": commit,
                                                            "command": f"python experiments/roofline.py --scene {scene}",
                                                            "transcribed_from_docs": False}))
    monkeypatch.setattr(RT, "RESULTS", results)
    for scene in "ab":
        monkeypatch.setitem(RT.SPECS, f"roofline-{scene}", RT.Spec("study", "x", csv="roofline.csv"))
    monkeypatch.setitem(RT.SPECS, "stack", RT.Spec("stack", "x", parts=(("A", "roofline-a"), ("B", "roofline-b")),
                                                   where=("default", "True"),
                                                   columns=(("width", "width"), ("ms", "seconds", 1e3), ("× bound", "ratio"))))
    lines = RT.render("stack")
    assert lines[:4] == ["| scene | width | ms | × bound |", "|---|---|---|---|", "| A | 256 | 27.9 | 2.6 |",
                         "| B | 256 | 45.7 | 2.6 |"]
    assert "2026-12-03" in lines[-1] and "at commit 0123456." in lines[-1]
    assert "--scene a`; `python experiments/roofline.py --scene b`" in lines[-1]
    assert "Sources: `results/roofline-a/`, `results/roofline-b/`" in lines[-1]
    (results / "roofline-b" / "roofline.csv").write_text("method,width,seconds,ratio,default\nlnf,64,0.5,9.0,False\n")
    with pytest.raises(RT.TableError, match="roofline-b/roofline.csv: no row with default = True"):
        RT.render("stack")


def test_a_table_of_quoted_cells_follows_the_tables_it_quotes(tmp_path, monkeypatch):
    """summary: each cell a template quoting other tables' cells, and ratios of two of them."""
    results = tmp_path / "results"
    (results / "runs").mkdir(parents=True)
    (results / "runs" / "table.csv").write_text("method,integrator,error\nours,midpoint,0.02\nours,rk4,0.03 / 0.05\n"
                                                "black box,rk4,0.06\n")
    (results / "runs" / "provenance.json").write_text(json.dumps({"machine": "m (2 cores), alone", "date": "2026-12-01",
                                                                 "command": "python run.py", "transcribed_from_docs": True}))
    (results / "digest").mkdir()
    cells = {"header": ["scene", "error", "reading"],
             "rows": [["a", "{runs|ours@midpoint|error} · {runs|ours@rk4|error#2}",
                       "{runs|black box|error ÷ runs|ours@midpoint|error}× better"]]}
    (results / "digest" / "cells.json").write_text(json.dumps(cells))
    monkeypatch.setattr(RT, "RESULTS", results)
    monkeypatch.setitem(RT.SPECS, "digest", RT.Spec("cells", "x"))
    lines = RT.render("digest")
    assert lines[2] == "| a | 0.02 · 0.05 | 3× better |"
    assert "Made on m (2 cores), 2026-12-01, by `python run.py`." in lines[-1] and "`results/runs/`" in lines[-1]
    assert "still transcribed from reports (runs)" in lines[-1]
    for bad, message in [("{runs|ours|error}", "has 2 rows 'ours'"), ("{runs|ours@rk4|speed}", "no column 'speed'"),
                         ("{nothing|a|b}", "no results/nothing/"), ("{runs|ours@rk4|error ÷ runs|black box|error}",
                                                                    "not a number")]:
        cells["rows"][0][1] = bad
        (results / "digest" / "cells.json").write_text(json.dumps(cells))
        with pytest.raises(RT.TableError, match=message):
            RT.render("digest")

"""`make bench` runs every benchmark that has defaults; the Makefile names the others with their argument."""

from __future__ import annotations

import re

from conftest import ROOT


def _makefile() -> str:
    return (ROOT / "Makefile").read_text()


def test_every_bench_script_is_run_by_make_bench_or_named_with_its_argument():
    text = _makefile()
    benches = re.search(r"^BENCHES := (.*?)(?<!\\)\n", text, re.MULTILINE | re.DOTALL)[1].replace("\\\n", " ").split()
    comment = " ".join(line for line in text.splitlines() if line.startswith("#"))
    scripts = sorted(p.name for p in (ROOT / "bench").iterdir() if p.suffix in (".py", ".sh"))
    assert all((ROOT / "bench" / f"{b}.py").is_file() for b in benches), benches
    unlisted = [s for s in scripts if s.removesuffix(".py") not in benches and s not in comment]
    assert unlisted == [], f"bench scripts neither in BENCHES nor named in the Makefile: {unlisted}"


def test_the_benches_make_runs_need_no_argument():
    text = _makefile()
    benches = re.search(r"^BENCHES := (.*?)(?<!\\)\n", text, re.MULTILINE | re.DOTALL)[1].replace("\\\n", " ").split()
    for name in benches:
        source = (ROOT / "bench" / f"{name}.py").read_text()
        positional = re.findall(r"add_argument\(\s*\"([^-][^\"]*)\"(?![^)]*nargs=\"[?*]\")", source)
        assert positional == [], f"bench/{name}.py needs {positional}: it cannot run with its defaults"

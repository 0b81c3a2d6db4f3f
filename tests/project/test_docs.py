"""The documentation cannot rot: its function examples run, its schemas and tutorial are real."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from engine.common.processes import listening_port
from engine.common.schemas import SchemaError, SchemaRegistry
from engine.language.mapping import compile_mapping, known_functions
from tests.support.repo import REPO
from tests.support.schemas import known_schema

DOCS = REPO / "docs"
ROW = re.compile(r"^\| `(?P<name>\w+)` \| `` (?P<expr>.+?) `` \| `(?P<result>.+?)` \| .* \|$")


@pytest.mark.fast
def test_every_function_is_documented_with_an_example_that_holds():
    text = (DOCS / "route-language.md").read_text()
    source = json.loads(text.split("## Functions", 1)[1].split("```json", 1)[1].split("```", 1)[0])
    rows = [ROW.match(line) for line in text.splitlines() if line.startswith("| `")]
    examples = {m["name"]: (m["expr"].replace("\\|", "|"), m["result"]) for m in rows if m and "(" in m["expr"]}
    assert sorted(examples) == known_functions()
    for name, (expression, result) in examples.items():
        value = compile_mapping(expression)(source)
        if result.startswith("<"):
            assert type(value).__name__ == {"<number>": "float", "<object>": "dict", "<string>": "str"}[result], name
        else:
            assert value == json.loads(result), f"{name}: {expression} gives {value!r}, the docs say {result}"


@pytest.mark.fast
def test_every_schema_is_documented():
    text = (DOCS / "schemas.md").read_text()
    for name in SchemaRegistry(REPO / "schemas").names():
        if ".v" in name:
            assert f"({name})" in text, name


@pytest.mark.fast
def test_the_tutorial_route_and_its_test_are_the_files_it_shows():
    tutorial = (DOCS / "tutorial.md").read_text()
    for name in ("tractor.yaml", "tractor.test.yaml", "sprayer.yaml", "sprayer.test.yaml"):
        assert (DOCS / "tutorial" / "routes" / name).read_text() in tutorial, name
    result = subprocess.run([sys.executable, "-m", "engine", "test", "--routes", "docs/tutorial/routes", "--schemas", "schemas"],
                            capture_output=True, text=True, cwd=REPO, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.splitlines()[-1] == "3 passed, 0 failed"
    assert "[docs/](docs/README.md)" in (REPO / "README.md").read_text()


def _anchors(text: str) -> set[str]:
    """GitHub's heading anchors (lowercase, punctuation dropped, spaces to hyphens) and explicit ids."""
    slugs = {re.sub(r"[^a-z0-9 _-]", "", line.lstrip("#").strip().lower()).replace(" ", "-")
             for line in text.splitlines() if line.startswith("#")}
    return slugs | set(re.findall(r'<a id="([^"]+)"></a>', text))


@pytest.mark.fast
def test_links_between_the_docs_resolve():
    """Every relative link of README.md and docs/*.md names a file that exists and, with a
    #fragment, a heading or anchor it has (route-language.md links into route-keys.md)."""
    broken = []
    for page in [REPO / "README.md", *sorted(DOCS.glob("*.md"))]:
        for target, fragment in re.findall(r"\]\(((?!https?:)[^)#\s]*)(?:#([^)\s]+))?\)", page.read_text()):
            linked = (page.parent / target).resolve() if target else page
            if not linked.exists() or (fragment and linked.suffix == ".md" and fragment not in _anchors(linked.read_text())):
                broken.append(f"{page.relative_to(REPO)}: {target}#{fragment}")
    assert broken == []
    assert "(route-keys.md)" in (DOCS / "route-language.md").read_text()


@pytest.mark.fast
def test_the_shared_types_are_defined_and_the_stamp_is_what_the_schemas_accept():
    """schemas.md defines every shared type of envelope.v1.json that the tables name, and what
    it says a stamp is (and is not) is what validation does."""
    text = (DOCS / "schemas.md").read_text()
    shared = json.loads((REPO / "schemas" / "envelope.v1.json").read_text())["$defs"]
    for name in set(shared) - {"header"}:
        assert f"### `{name}`" in text, name
    position = known_schema(SchemaRegistry(REPO / "schemas"), "position")
    fix = {"agent_id": "uav1", "lat": -22.0, "lon": -47.9}
    position.validate({**fix, "stamp": {"sec": 1700000000, "nanosec": 500000000}})
    stamp_section = text.split("### `stamp`", 1)[1].split("###", 1)[0]
    for refused, shown in ((1700000000.5, "`1700000000.5`"), ("2023-11-14T22:13:20Z", "ISO 8601"), ({"sec": 1700000000}, "`{sec}` without")):
        assert shown in stamp_section
        with pytest.raises(SchemaError):
            position.validate({**fix, "stamp": refused})
    assert "UNIX seconds" not in text.split("| `stamp` |", 1)[1].split("\n", 1)[0]


FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
CREATE = re.compile(r"Create `(my-routes/[^`]+)`[^\n]*:\n\n$")


def tutorial_script(text: str, work: Path, port: int) -> tuple[str, list[str]]:
    """Steps 2 to 4 of the tutorial as one bash script, in the order the reader meets them:
    each ```bash block as it is, and each file the reader is told to create (the ```yaml block
    after "Create `my-routes/...`") written by a heredoc. The expected output the blocks show as
    comments (``# 2 passed, 0 failed``; ``...`` stands for anything) is returned for checking.
    Only what would collide with a parallel run changes: port 9180 and /tmp/."""
    script = ["set -e", "trap 'kill $(jobs -p) 2>/dev/null || true' EXIT  # a failed step stops what runs in the background"]
    expected: list[str] = []
    body = text[text.index("## 2."):]
    for match in FENCE.finditer(body):
        language, block = match.groups()
        created = CREATE.search(body[:match.start()])
        if language == "yaml" and created:
            script.append(f"mkdir -p my-routes\ncat > {created[1]} <<'YAML'\n{block}YAML")
        elif language == "bash":
            script.append(block.replace("9180", str(port)).replace("/tmp/", f"{work}/"))
            expected += [line[2:] for line in block.splitlines() if line.startswith("# ")]
    return "\n".join(script) + "\n", expected


def stop_group(pgid: int, timeout: float = 60) -> None:
    """Stop whatever of the script's process group still runs (an engine stops its private
    broker on SIGTERM: never leave one behind), SIGKILL after ``timeout``."""
    deadline = time.monotonic() + timeout
    signal_to_send: signal.Signals | int = signal.SIGTERM
    while time.monotonic() < deadline + 10:  # a zombie nobody reaps still answers: give up then
        try:
            os.killpg(pgid, signal_to_send)
        except ProcessLookupError:
            return
        signal_to_send = signal.SIGKILL if time.monotonic() > deadline else 0
        time.sleep(0.2)  # pacing: the signals to a process group until it is gone


@pytest.mark.soak
@pytest.mark.timeout(400)  # the tutorial script's own bound is 320 s
def test_the_tutorial_steps_work_as_written(tmp_path: Path):
    """Steps 2 to 4 run exactly as the tutorial shows them, in order (step 1 is scripts/setup.sh,
    which this machine has run): check and test print what the tutorial says, the engine runs
    with its private broker, the tap listens and gets both messages, the edit is reloaded, and
    the engine stops. The typo and the broken expectation it shows give the output it shows."""
    text = (DOCS / "tutorial.md").read_text()
    work = tmp_path / "farm"
    work.mkdir()
    (work / "schemas").symlink_to(REPO / "schemas")
    port = listening_port()
    script, expected = tutorial_script(text, work, port)
    (work / "tutorial.sh").write_text(script)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",
           "PYTHONPATH": f"{REPO}:{os.environ.get('PYTHONPATH', '')}".rstrip(":")}
    env.pop("RABBITROS_AMQP_URL", None)
    shell = subprocess.Popen(["timeout", "-s", "KILL", "300", "bash", "tutorial.sh"], cwd=work, env=env, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        out, _ = shell.communicate(timeout=320)
    finally:
        stop_group(shell.pid)
    log = (work / "engine.log").read_text() if (work / "engine.log").exists() else ""
    assert shell.returncode == 0, out + log
    for line in expected:
        assert re.search("^" + re.escape(line).replace(r"\.\.\.", ".*") + "$", out, re.M), f"{line!r} not in:\n{out}"
    taps = [json.loads(line) for line in out.splitlines() if line.startswith('{"ts"')]
    assert [tap["outcome"] for tap in taps] == ["delivered", "dead_lettered"], out
    assert taps[0]["canonical"]["alt_msl"] == 612.5 and taps[1]["error"].startswith("mapping:")
    assert "generation 2" in out and 'rabbitros_messages_total{outcome="delivered",route="tractor-position"} 1.0' in out
    assert "listening" in (work / "tap.log").read_text()
    assert "stopped" in log.splitlines()[-2] + log.splitlines()[-1], log[-2000:]

    def engine(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["rabbitros-engine", *args, "--routes", "my-routes", "--schemas", "schemas"],
                              cwd=work, env=env, capture_output=True, text=True, timeout=60)

    route = work / "my-routes" / "tractor.yaml"
    route.write_text((DOCS / "tutorial" / "routes" / "tractor.yaml").read_text().replace("schema: position", "schema: positon"))
    typo_line = re.search(r"`check` says `(.+?)`\.", text.replace("\n", " "))
    assert typo_line is not None, "the tutorial shows what `check` says about the typo"
    typo = typo_line[1]
    assert re.fullmatch(re.escape(typo).replace(r"\(\.\.\.\)", r"\(.*\)"), engine("check").stderr.strip())
    route.write_text((DOCS / "tutorial" / "routes" / "tractor.yaml").read_text())
    cases = work / "my-routes" / "tractor.test.yaml"
    cases.write_text(cases.read_text().replace("alt_msl: 612.5}", "alt_msl: 6125}"))
    failed = engine("test")
    shown_block = re.search(r"e\.g\.\n`alt_msl: 6125`:\n\n```\n(.*?)```", text, re.S)
    assert shown_block is not None, "the tutorial shows what `test` prints for the failing case"
    shown = shown_block[1]
    assert failed.returncode == 1 and shown in failed.stdout, failed.stdout

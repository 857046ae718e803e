"""`nprt --version`, `nprt jobs ...` against a live server, logging flags, and defaults in
every --help."""

from __future__ import annotations

import argparse
import json
import logging
from importlib.metadata import version

import pytest

from nprt.service.cli import build_parser, log_level, main
from tests.service.helpers import TINY, HeldSlots, wait_for


@pytest.fixture
def restore_logging():
    """main() installs its console handler; put the root logger back afterwards."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for h in list(root.handlers):
        if h not in handlers:
            root.removeHandler(h)
    root.setLevel(level)


@pytest.fixture(scope="module")
def done_job(client):
    job = client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()
    return wait_for(lambda: (j := client.get(f"/v1/jobs/{job['id']}").json())["state"]
                    == "succeeded" and j, 120, what="job succeeds")


def _nprt(capsys, *argv) -> tuple[int, str, str]:
    rc = main(list(argv))
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_version_prints_the_installed_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"nprt {version('nprt')}"


def test_jobs_list_shows_each_job_and_filters_by_state(live, done_job, capsys,
                                                       restore_logging):
    rc, out, err = _nprt(capsys, "jobs", "list", "--server", live.url)
    assert rc == 0
    header, *rows = out.splitlines()
    assert header.split() == ["ID", "STATE", "SCENE", "SETTINGS", "DONE", "AGE", "DURATION"]
    row = next(r for r in rows if r.startswith(done_job["id"][:8]))
    assert row.split()[1:7] == ["succeeded", "forest:tiny", "32x32", "4spp", "exact", "ref"]
    assert row.split()[7] == "100%"
    assert "job(s), from offset 0" in err
    rc, out, _ = _nprt(capsys, "jobs", "list", "--state", "failed", "--server", live.url,
                       "--json")
    assert rc == 0 and json.loads(out)["data"] == []


def test_jobs_show_accepts_a_prefix(live, done_job, capsys, restore_logging):
    rc, out, _ = _nprt(capsys, "jobs", "show", done_job["id"][:6], "--server", live.url)
    assert rc == 0
    fields = dict(line.strip().split("  ", 1) for line in out.splitlines())
    assert fields["id"] == done_job["id"] and fields["state"].strip() == "succeeded"
    assert fields["settings"].strip() == "32x32 4spp exact ref"
    assert fields["progress"].strip() == "8 of 8 passes"
    assert fields["duration"].strip().endswith(" s")


def test_jobs_show_unknown_id_is_one_line_exit_2(live, capsys, restore_logging):
    rc, out, err = _nprt(capsys, "jobs", "show", "feedbeef", "--server", live.url)
    assert rc == 2 and out == ""
    assert err.startswith("nprt: job id: feedbeef: no job among the newest 500")
    assert len(err.strip().splitlines()) == 1
    rc, _, err = _nprt(capsys, "jobs", "show", "f" * 32, "--server", live.url)
    assert rc == 2 and "404" in err and "no job with id" in err


def test_jobs_logs_prints_the_job_log_and_follows_to_the_end(live, client, done_job, capsys,
                                                             restore_logging):
    whole = client.get(f"/v1/jobs/{done_job['id']}/logs").text
    rc, out, _ = _nprt(capsys, "jobs", "logs", done_job["id"], "--server", live.url)
    assert rc == 0 and out == whole and "preparing scene" in out
    rc, out, _ = _nprt(capsys, "jobs", "logs", "-f", done_job["id"], "--server", live.url)
    assert rc == 0 and out == whole


def test_jobs_cancel_then_wait_exits_1_and_wait_on_success_exits_0(live, done_job, capsys,
                                                                   restore_logging):
    held = HeldSlots(live.url, live.settings.max_concurrent_jobs)
    try:
        rc, out, _ = _nprt(capsys, "jobs", "cancel", held.ids[0], "--server", live.url)
        assert rc == 0 and out.split()[0] == held.ids[0]
        rc, out, _ = _nprt(capsys, "jobs", "wait", held.ids[0], "--quiet", "--server",
                           live.url)
        assert rc == 1 and out.strip() == f"{held.ids[0]} canceled"
        rc, _, err = _nprt(capsys, "jobs", "cancel", held.ids[0], "--server", live.url)
        assert rc == 2 and "409" in err and "already canceled" in err
    finally:
        held.release()
    rc, out, _ = _nprt(capsys, "jobs", "wait", done_job["id"], "--server", live.url)
    assert rc == 0 and out.strip() == f"{done_job['id']} succeeded"


def test_jobs_against_no_server_is_one_line_exit_2(capsys, restore_logging):
    rc, out, err = _nprt(capsys, "jobs", "list", "--server", "http://127.0.0.1:9")
    assert rc == 2 and out == ""
    assert err.startswith("nprt: cannot reach the server: http://127.0.0.1:9: ")


@pytest.mark.parametrize("argv,expected", [
    (["scenes"], "WARNING"), (["-v", "scenes"], "INFO"), (["serve"], "INFO"),
    (["serve", "--log-level", "debug"], "DEBUG"), (["--log-level", "ERROR", "serve"], "ERROR"),
    (["--log-level", "error", "render", "forest"], "ERROR")])
def test_log_level_flag_wins_over_the_command_default(argv, expected):
    assert log_level(build_parser().parse_args(argv)) == expected


def test_log_level_and_json_logs_reach_stderr(capsys, restore_logging):
    rc, _, err = _nprt(capsys, "--log-level", "INFO", "--log-json", "scenes", "--sizes", "tiny")
    assert rc == 0
    records = [json.loads(line) for line in err.splitlines()]
    assert any(r["logger"] == "nprt.scene.demos" and r["level"] == "INFO" for r in records)
    assert all({"time", "level", "logger", "message", "thread"} <= r.keys() for r in records)
    rc, _, err = _nprt(capsys, "scenes", "--sizes", "tiny")
    assert rc == 0 and err == ""  # WARNING by default: the INFO records stay quiet


def _parsers(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_every_help_shows_every_default():
    checked = 0
    for parser in _parsers(build_parser()):
        text = " ".join(parser.format_help().split())
        for action in parser._actions:
            if (action.option_strings and action.nargs != 0
                    and action.default not in (None, argparse.SUPPRESS)):
                assert action.help, f"{parser.prog} {action.option_strings}: no help"
                shown = " ".join(str(action.default).split())
                assert f"(default: {shown})" in text, (parser.prog, action.option_strings)
                checked += 1
    assert checked > 50

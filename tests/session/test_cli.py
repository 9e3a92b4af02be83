"""The command line's release basics: --version, -v/-q to logging, a closed pipe,
`view` without a display, and its defaults as docs/config.md states them."""

from __future__ import annotations

import logging
import re
import shutil
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import crossfield
from crossfield.cli import build_parser, main
from crossfield.cli.common import log_level
from crossfield.cli.session import resolve_run_config
from crossfield.config import DEFAULT_PLUGINS, SESSION_DEFAULTS
from crossfield.chain.registry import STAGES, get_implementation, make_plugin_manager

REPO = Path(__file__).resolve().parents[2]


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"crossfield {crossfield.__version__}"


def test_the_parser_loads_no_pipeline():
    """``crossfield --help`` and ``--version`` build the parser of every command without
    importing what the commands run: the chain, Dask, Rerun, the recording's codecs,
    scipy.stats (each command imports those when it runs; crossfield/cli/__init__.py)."""
    heavy = ("crossfield.chain.runner", "crossfield.recording.codec", "distributed", "rerun", "scipy.stats")
    probe = (
        "import sys; from crossfield.cli import build_parser; build_parser(); "
        f"print(' '.join(m for m in {heavy!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == []


def test_closed_pipe_ends_quietly():
    """The reader is gone before the first line is written: no traceback, the
    status of a command stopped by SIGPIPE."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "crossfield.cli", "plugins"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    proc.stdout.close()  # before the child has imported anything, let alone written
    _, err = proc.communicate(timeout=120)
    assert err.decode() == ""
    assert proc.returncode == 128 + signal.SIGPIPE


@pytest.mark.skipif(shutil.which("head") is None, reason="needs head(1)")
def test_plugins_into_head():
    proc = subprocess.run(
        f"{sys.executable} -m crossfield.cli plugins | head -1", shell=True, capture_output=True, text=True,
        timeout=120, check=False,
    )
    assert proc.stdout == "acquire:\n"
    assert proc.stderr == ""


def test_log_levels():
    assert log_level() == logging.WARNING
    assert log_level(verbose=1) == logging.INFO
    assert log_level(verbose=2) == log_level(verbose=5) == logging.DEBUG
    assert log_level(verbose=2, quiet=1) == logging.ERROR


@pytest.mark.parametrize(
    ("flags", "info", "debug"),
    [((), False, False), (("-v",), True, False), (("-vv",), True, True), (("-q",), False, False)],
)
def test_verbosity_flags_set_the_crossfield_loggers(tmp_path, capsys, flags, info, debug):
    root = logging.getLogger("crossfield")
    handlers = list(root.handlers)
    # run with a config error after the config is resolved: logging, then exit 2
    status = main(["run", *flags, "--centroid", "nope", "-o", str(tmp_path), "--frames", "1", "--no-rerun"])
    assert status == 2
    err = capsys.readouterr().err
    config_line = "crossfield.cli.session: info: config <defaults> (with command-line overrides): acquire=simulator"
    assert (config_line in err) == info
    assert ("crossfield.cli.session: debug: resolved config:" in err) == debug
    assert "crossfield: error: no centroid implementation named 'nope'" in err  # errors are always shown
    assert root.handlers == handlers  # the command's handler is gone again


def test_one_logger_per_module(caplog, tmp_path):
    import crossfield.cli.common as cli_module

    caplog.set_level(logging.DEBUG, logger="crossfield")
    assert main(["plugins", "-vv"]) == 0
    names = {r.name for r in caplog.records}
    assert cli_module.logger.name == cli_module.__name__ == "crossfield.cli.common"
    assert "crossfield.cli.common" in names
    assert all(n.startswith("crossfield.") for n in names)


def test_view_without_a_display_names_web_and_screenshot(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is Linux's $DISPLAY / $WAYLAND_DISPLAY")
    session = tmp_path / "session.rrd"
    session.write_bytes(b"")  # never opened: the display is checked first
    assert main(["view", str(session)]) == 2
    err = capsys.readouterr().err
    assert "no display" in err and "--web" in err and "--screenshot" in err
    assert "Traceback" not in err
    assert main(["view", str(tmp_path / "missing.rrd")]) == 2  # a wrong path is named first
    assert "missing.rrd: no such file" in capsys.readouterr().err


# --------------------------------------------------------------------------
# The config assembly (shared with crossfield.run) and the documented defaults
# --------------------------------------------------------------------------


def run_config(*flags: str):
    return resolve_run_config(build_parser().parse_args(["run", *flags]))


def test_flags_and_api_arguments_give_one_config(tmp_path):
    flags = [
        "--scenario", "table3", "--frames", "3", "--seed", "7", "-o", str(tmp_path), "--name", "x",
        "--no-record", "--no-rerun", "--centroid", "ellipse", "--register", "horn",
        "--option", "centroid.threshold_sigma=7.5", "--option", "session.rerun_image_every=2",
    ]
    api = crossfield.run_config(
        scenario="table3", frames=3, seed=7, output_dir=tmp_path, name="x", record=False, rerun=False,
        centroid="ellipse", register="horn",
        options={"centroid": {"threshold_sigma": 7.5}, "session": {"rerun_image_every": 2}},
    )
    assert api.to_dict() == run_config(*flags).to_dict()


def test_the_config_keeps_the_users_reference_port_and_adds_none():
    # With no port named the runner reads the arm the simulator serves
    # (crossfield.stages.ServesSimulatedArm; tests/structure/test_structure.py, test_cmm_link.py).
    assert run_config().stages["reference"].options == {}
    assert run_config("--option", "reference.port=/dev/ttyUSB0").stages["reference"].options == {
        "port": "/dev/ttyUSB0"
    }
    assert "port" not in run_config("--reference", "csv").stages["reference"].options
    assert "port" not in run_config("--acquire", "folder").stages["reference"].options


def test_simulator_flags_need_the_simulator(capsys):
    assert main(["run", "--acquire", "folder", "--frames", "2", "-q"]) == 2
    assert "--frames applies to the simulator source, not to 'folder'" in capsys.readouterr().err


def _toml_block(doc: Path) -> dict:
    match = re.search(r"```toml\n(.*?)```", doc.read_text(), re.S)
    assert match, doc
    return tomllib.loads(match.group(1))


def test_docs_config_states_the_programs_defaults():
    """Every value in docs/config.md's default config is what the program uses."""
    documented = _toml_block(REPO / "docs" / "config.md")
    program = run_config()  # `crossfield run` without flags
    assert documented["session"] == SESSION_DEFAULTS == dict(program.session)
    pm = make_plugin_manager()
    for stage in STAGES:
        table = dict(documented[stage])
        assert table.pop("plugin") == DEFAULT_PLUGINS[stage] == program.stages[stage].plugin, stage
        defaults = get_implementation(pm, stage, DEFAULT_PLUGINS[stage]).options()
        for key, value in table.items():
            given = program.stages[stage].options.get(key, defaults.get(key))
            assert value == given, f"docs/config.md [{stage}] {key} = {value!r}; the program uses {given!r}"


def test_user_guide_states_the_default_scenario():
    text = (REPO / "docs" / "user-guide.md").read_text()
    pm = make_plugin_manager()
    scenario = get_implementation(pm, "acquire", "simulator").options()["scenario"]
    assert f"With no arguments it runs the built-in simulator (`{scenario}` scenario)" in text
    assert "crossfield run --scenario table3" in (REPO / "Makefile").read_text()


def test_user_guide_states_the_defaults():
    text = " ".join((REPO / "docs" / "user-guide.md").read_text().split())
    defaults = get_implementation(make_plugin_manager(), "acquire", "simulator").options()
    assert f"`{defaults['scenario']}` (default)" in text
    frames, seed = defaults["frames"], defaults["seed"]
    assert f"number of stereo pairs (default {frames}), noise seed (default {seed})" in text
    assert f"where session folders go (default `{SESSION_DEFAULTS['output_dir']}/`)" in text
    view = build_parser().parse_args(["view", "x"])
    assert f"`--port {view.port}`, `--window-size {view.window_size}`" in text


@pytest.mark.parametrize("argv, verbose", [
    (["batch", "-v", "audit", "x.mcap"], 1),
    (["batch", "audit", "-v", "x.mcap"], 1),
    (["batch", "-vv", "compare", "x.mcap"], 2),
    (["batch", "replay", "x.mcap"], 0),
])
def test_batch_verbosity_is_kept_on_either_side_of_the_kind(argv, verbose) -> None:
    from crossfield.cli import build_parser

    args = build_parser().parse_args(argv)
    assert args.verbose == verbose and args.quiet == 0

"""``crossfield calibrate`` and ``crossfield verify`` (``docs/calibration.md``)."""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.cli.common import Command
from crossfield.config import DEFAULT_PLUGINS, load_config, parse_option
from crossfield.errors import ConfigError, CrossfieldError
from crossfield.recording.seal import load_private_key

__all__ = ["COMMANDS"]


def add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--images", metavar="DIR", help="folder of image pairs (upper_0000.png / lower_0000.png)"
    )
    src.add_argument("--scenario", help="simulated views of a simulator scenario's rig (station or table3)")
    src.add_argument(
        "--replay",
        metavar="CAL.mcap",
        help="calibrate again from a recorded calibration's raw images (recorded board and settings "
        "unless --board / --distortion are given)",
    )
    src.add_argument(
        "--source",
        choices=("basler", "opencv"),
        help="live cameras through that acquire plugin; its options as for `crossfield run` "
        "(-c CONFIG [acquire] table, --option acquire.KEY=VALUE); Enter takes a pair, q ends",
    )
    live = parser.add_argument_group("live cameras (--source)")
    live.add_argument(
        "-c", "--config", metavar="FILE", help="session config whose [acquire] table has the source's options"
    )
    live.add_argument(
        "--option", action="append", default=[], metavar="acquire.KEY=VALUE",
        help="set a source option, e.g. acquire.upper='\"40012345\"' (repeatable)",
    )
    when = live.add_mutually_exclusive_group()
    when.add_argument(
        "--every", type=float, metavar="SECONDS", help="take a pair every SECONDS (no key needed)"
    )
    when.add_argument(
        "--trigger", action="store_true",
        help="take every pair the source delivers (basler: trigger = hardware, a pair per trigger pulse)",
    )
    live.add_argument(
        "--pairs", type=int, default=0, metavar="N", help="end after N pairs (default: until q or Ctrl-C)"
    )
    live.add_argument(
        "--view", nargs="?", const="new", metavar="URL",
        help="show the coverage live in a Rerun viewer: a new native one, or the running one at URL",
    )
    live.add_argument("--rrd", metavar="FILE.rrd", help="save the live coverage view to a Rerun file")
    live.add_argument("--no-window", action="store_true", help="no OpenCV window even if a display is there")
    parser.add_argument(
        "--board",
        metavar="BOARD.toml",
        help="board definition ([board], optional [calibration]); default: ChArUco 11x8, 15 mm",
    )
    parser.add_argument("-o", "--output", metavar="CALIB.yml", required=True, help="calibration file to write")
    parser.add_argument(
        "--pattern", default="{camera}_{seq}.png", help="image file-name pattern (as the folder source)"
    )
    parser.add_argument(
        "--bit-depth", type=int, help="significant bits of 16-bit images (default: from the pixel values)"
    )
    parser.add_argument(
        "--distortion", choices=("plumb_bob", "rational"), help="distortion model (default plumb_bob)"
    )
    parser.add_argument("--views", type=int, default=20, help="simulated views (--scenario; default 20)")
    parser.add_argument("--seed", type=int, default=1, help="noise seed of the simulated views (default 1)")
    parser.add_argument(
        "--outlier-views",
        type=int,
        nargs="*",
        default=[],
        metavar="K",
        help="simulated views in which the board moves between the two exposures",
    )
    parser.add_argument("--save-images", metavar="DIR", help="also write the simulated or live views as image pairs")
    parser.add_argument("--no-report", action="store_true", help="do not write the report")
    parser.add_argument(
        "--cross-validate",
        action="store_true",
        help="also calibrate two halves of the views and compare them against their stated uncertainty",
    )
    parser.add_argument(
        "--record", metavar="CAL.mcap",
        help="record the session (images, detections, result) to MCAP (--source: default <CALIB>.mcap)",
    )
    _add_signing_key(parser)


def _add_signing_key(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--signing-key", metavar="KEY.pem",
        help="sign the recording's seal with this Ed25519 station key (crossfield keygen; needs --record)",
    )


def _check_signing_key(args: argparse.Namespace, records: bool) -> None:
    """``--signing-key`` checked before anything is computed: it needs a recording
    (``records``), and a key that cannot be read is a one-line
    :class:`crossfield.recording.seal.SealError` naming the file."""
    if args.signing_key:
        if not records:
            raise ConfigError("--signing-key signs a recording: give --record as well")
        load_private_key(args.signing_key)


def add_verify_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", help="simulator scenario providing the scale-bar positions (default station)"
    )
    parser.add_argument(
        "--recording",
        metavar="VERIFY.mcap",
        help="evaluate the scale-bar pairs of a recorded verification (crossfield verify --record) again, "
        "with --calibration; bar length, its u and the MPE as recorded unless given",
    )
    parser.add_argument("--calibration", metavar="CALIB.yml", required=True, help="the calibration to verify")
    parser.add_argument(
        "--mpe", type=float, help="maximum permissible length error E_MPE (mm, default 0.1)"
    )
    parser.add_argument("--bar-mm", type=float, help="certified scale-bar length (mm, default 100)")
    parser.add_argument(
        "--bar-u-mm", type=float, help="standard uncertainty of the certified length (mm, default 0.002)"
    )
    parser.add_argument("--frames", type=int, default=3, help="stereo pairs per position (default 3)")
    parser.add_argument("--seed", type=int, default=1, help="noise seed (default 1)")
    parser.add_argument(
        "--record", metavar="VERIFY.mcap", help="record the session (pairs, bar, results) to MCAP"
    )
    parser.add_argument(
        "-o", "--output", metavar="OUT", default="verification", help="report stem (default verification)"
    )
    parser.add_argument("--operator", metavar="NAME", help="who ran the verification (stated in the record's header)")
    _add_signing_key(parser)


def _board_and_settings(path: str | None, distortion: str | None):
    from crossfield.calibration.boards import Board, board_from_dict, read_board_file
    from crossfield.calibration.solve import CalibrationSettings, settings_from_dict
    board, settings = Board(), CalibrationSettings()
    if path:
        data = read_board_file(path)
        board = board_from_dict(data["board"], path)
        settings = settings_from_dict(data.get("calibration", {}), path)
    if distortion:
        settings = replace(settings, distortion=distortion)
    return board, settings


def cmd_calibrate(args: argparse.Namespace) -> int:
    from crossfield.calibration.crossval import summary_line
    from crossfield.calibration.file import write_calibration_result
    from crossfield.calibration.images import read_image_pairs, write_image_pairs
    from crossfield.calibration.record import read_calibration_recording, record_calibration
    from crossfield.calibration.report import write_report
    from crossfield.calibration.solve import calibrate_images
    from crossfield.simulator.board_views import cached_calibration_views
    board, settings = _board_and_settings(args.board, args.distortion)
    if not args.source:
        live_only = {"--config": args.config, "--option": args.option, "--every": args.every is not None,
                     "--trigger": args.trigger, "--pairs": args.pairs, "--view": args.view, "--rrd": args.rrd}  # fmt: skip
        given = [flag for flag, value in live_only.items() if value]
        if given:
            raise ConfigError(f"{given[0]} applies to live cameras (--source) only")
    if args.record and Path(args.record).exists():  # refused before the solve, not after it
        raise ConfigError(f"--record: {args.record} exists; a recording is not overwritten")
    _check_signing_key(args, bool(args.record or args.source))  # --source records by default
    if args.replay:
        recorded = read_calibration_recording(args.replay)
        images, bit_depth, names = recorded.images, recorded.bit_depth, recorded.names
        if not args.board:
            board, settings = recorded.board, recorded.settings
            if args.distortion:
                settings = replace(settings, distortion=args.distortion)
        source = f"crossfield calibrate --replay {args.replay}"
    elif args.scenario:
        try:
            views = cached_calibration_views(
                args.scenario, args.views, args.seed, board, tuple(args.outlier_views)
            )
        except ValueError as exc:
            raise ConfigError(f"--scenario: {exc}") from None
        images, bit_depth = views.images, views.bit_depth
        names = [f"sim view {k}" for k in range(len(images))]
        source = f"crossfield calibrate --scenario {args.scenario}"
        if args.save_images:
            write_image_pairs(args.save_images, images)
    elif args.source:
        images, bit_depth, names, source = _live_pairs(args, board, settings)
        if args.record is None:
            args.record = str(Path(args.output).with_suffix(".mcap"))
        if args.save_images:
            write_image_pairs(args.save_images, images)
        if len(images) < settings.min_views:
            print(
                f"crossfield: {len(images)} pairs taken, at least {settings.min_views} needed "
                f"(min_views): no calibration written",
                file=sys.stderr,
            )
            return 2
    else:
        pairs = read_image_pairs(args.images, args.pattern, args.bit_depth)
        images, bit_depth, names = pairs.images, pairs.bit_depth, pairs.names
        source = f"crossfield calibrate --images {args.images}"
    if args.cross_validate:
        settings = replace(settings, cross_validate=True)
    result = calibrate_images(images, board, bit_depth, settings, names=names, source=source)
    out = write_calibration_result(args.output, result)
    if args.record:
        sealed = record_calibration(
            args.record, images, names, bit_depth, result, source, signing_key=args.signing_key
        )
    c = result.calibration
    print(f"calibration written to {out}")
    print(
        f"  views: {len(images)} pairs, {len(result.used_stereo)} used in the stereo solution, "
        f"{len(result.held_out)} held out, {len({d.view for d in result.dropped if d.stage != 'detect'})} dropped"
    )
    for d in result.dropped:
        print(f"  dropped {d.name} ({d.stage}): {d.reason}")
    print(
        f"  RMS reprojection error: upper {result.cameras['upper'].rms_px:.4f} px, lower "
        f"{result.cameras['lower'].rms_px:.4f} px, stereo {result.rms_stereo_px:.4f} px"
    )
    for cam in ("upper", "lower"):
        K = c.camera(cam).camera_matrix
        std = result.std_by_name()
        print(
            f"  {cam}: fx {K[0, 0]:.2f} +- {std[cam + '.fx']:.2f} px, fy {K[1, 1]:.2f} +- {std[cam + '.fy']:.2f} px, "
            f"cx {K[0, 2]:.2f} +- {std[cam + '.cx']:.2f} px, cy {K[1, 2]:.2f} +- {std[cam + '.cy']:.2f} px"
        )
    print(f"  baseline |T| = {result.baseline_mm:.4f} +- {result.baseline_std_mm:.4f} mm")
    if result.cross_validation is not None:
        print(f"  {summary_line(result.cross_validation)}")
    for k, (rms, mx) in sorted(result.holdout_epipolar_px.items()):
        print(f"  held-out {result.view_names[k]}: epipolar error RMS {rms:.3f} px, max {mx:.3f} px")
    if not args.no_report:
        stem = out.with_name(out.stem + "-report")
        for path in write_report(result, stem, calibration_path=out, seal=sealed if args.record else None):
            print(f"  report: {path}")
    if args.record:
        print(
            f"  recorded to {args.record} (chain head {sealed.chain_head}{_signed(sealed)}; "
            f"audit: crossfield audit {args.record})"
        )
    return 0


def _signed(sealed) -> str:
    """', signed' when the seal carries the station key's signature."""
    return ", signed" if sealed.signature else ""


def _live_options(args: argparse.Namespace) -> dict:
    """The source's options as `crossfield run` reads them (the config file's [acquire] table, then
    --option acquire.KEY=VALUE), plus the live defaults: frames = 0 (until stopped); --trigger:
    trigger = hardware (basler). The table's plugin, if named, must be the --source."""

    acquire = load_config(args.config).stages["acquire"]
    if acquire.plugin not in (args.source, DEFAULT_PLUGINS["acquire"]):
        raise ConfigError(
            f"{args.config}: [acquire] plugin is {acquire.plugin!r}, but --source is {args.source!r}"
        )
    options = dict(acquire.options)
    for text in args.option:
        stage, key, value = parse_option(text)
        if stage != "acquire":
            raise ConfigError(f"--option {text!r}: calibrate takes source options only (acquire.KEY=VALUE)")
        options[key] = value
    options.setdefault("frames", 0)
    if args.trigger and args.source == "basler":
        options.setdefault("trigger", "hardware")
    return options


def _live_pairs(args: argparse.Namespace, board, settings):
    """Open the live source, take pairs (crossfield.calibration.live), close it:
    (images, bit_depth, names, source text)."""
    from crossfield.calibration.coverage import coverage_line
    from crossfield.calibration.live import CoverageLog, CoverageWindow, KeyEvents, capture_live, print_pair, window_available, write_provisional_calibration
    from crossfield.viz.view import spawn_live_viewer

    if args.pairs < 0:
        raise ConfigError(f"--pairs must be >= 0, got {args.pairs}")
    if args.every is not None and not args.every > 0:
        raise ConfigError(f"--every must be a positive number of seconds, got {args.every}")
    options = _live_options(args)
    mode = "trigger" if args.trigger else "every" if args.every is not None else "key"
    upper, lower = options.get("upper"), options.get("lower")
    free_running = (args.source == "basler" and options.get("trigger") == "hardware") or (
        args.source == "opencv" and (isinstance(upper, int) or isinstance(lower, int))
    )
    implementation = get_implementation(make_plugin_manager(), "acquire", args.source)
    views = []
    with tempfile.TemporaryDirectory(prefix="crossfield-calibrate-") as tmp:
        if "calibration" not in options:
            options["calibration"] = str(write_provisional_calibration(Path(tmp) / "provisional.yml"))
        source = implementation.create(options, f"--source {args.source}")
        try:
            events = KeyEvents(sys.stdin)
            window = None if args.no_window or not window_available() else CoverageWindow(events)
            if window is not None:
                views.append(window)
            if args.view or args.rrd:
                viewer = None
                if args.view:
                    viewer = spawn_live_viewer() if args.view == "new" else args.view
                views.append(CoverageLog(args.rrd, viewer=viewer))

            def on_pair(pair, coverage):
                print_pair(pair, coverage)
                for view in views:
                    view(pair, coverage)

            if mode == "key":
                how = "Enter" + (" (or space in the window)" if window else "")
                how += " takes a pair, q then Enter ends"
            elif mode == "every":
                how = f"a pair every {args.every:g} s, q then Enter ends"
            else:
                how = "a pair per trigger, q then Enter or Ctrl-C ends"
            print(f"calibrate from the {args.source} source: {how}", flush=True)
            frames = source.frames()
            try:
                live = capture_live(
                    frames, board, events, mode=mode, every_s=args.every or 0.0, pairs=args.pairs,
                    free_running=free_running, min_points=min(settings.min_points, 6), on_pair=on_pair,
                    idle=None if window is None else window.poll, stop=source.stop,
                )
            finally:
                with contextlib.suppress(ValueError):  # a reader thread that did not end in time
                    frames.close()
        finally:
            source.close()
            for view in views:
                close = getattr(view, "close", None)
                if close is not None:
                    close()
    print(f"{len(live.images)} pairs taken (ended by {live.ended_by})")
    if live.coverage:
        print(f"  coverage: {coverage_line(live.coverage)}")
    text = f"crossfield calibrate --source {args.source} ({mode}"
    text += f" every {args.every:g} s)" if mode == "every" else ")"
    return list(live.images), live.bit_depth, list(live.names), text


def cmd_verify(args: argparse.Namespace) -> int:
    """``crossfield verify``: the simulated bar of ``--scenario`` (default station) or the
    pairs of ``--recording``; ``--record`` writes the session."""
    from crossfield.camera.calibration_io import read_stereo_calibration
    from crossfield.report.vocabulary import verdict_word
    from crossfield.simulator.scenarios import SCENARIOS, station_calibration
    from crossfield.verification.procedure import create_stages, evaluate, simulate_positions
    from crossfield.verification.record import read_verification_recording, record_verification
    from crossfield.verification.report import write_verification

    if args.recording and args.scenario:
        raise CrossfieldError("--recording and --scenario: give one (the recording holds its own pairs)")
    if args.record and Path(args.record).exists():
        raise CrossfieldError(f"--record: {args.record} exists; a recording is not overwritten")
    _check_signing_key(args, bool(args.record))

    recorded = read_verification_recording(args.recording) if args.recording else None
    bar_mm = args.bar_mm if args.bar_mm is not None else recorded.certified_mm if recorded else 100.0
    bar_u_mm = args.bar_u_mm if args.bar_u_mm is not None else recorded.certified_u_mm if recorded else 0.002
    mpe = args.mpe if args.mpe is not None else recorded.mpe_mm if recorded else 0.1
    if not mpe > 0 or not bar_mm > 0 or args.frames < 1:
        raise CrossfieldError("--mpe and --bar-mm must be > 0 and --frames >= 1")
    if recorded is not None:
        frames = recorded.named_frames
        specs = recorded.stages
        first = frames[0][1][0] if frames and frames[0][1] else None
        sizes = None if first is None else tuple((f.shape[1], f.shape[0]) for f in (first.upper, first.lower))
        source = f"crossfield verify --recording {args.recording}"
    else:
        scenario = args.scenario or "station"
        if scenario not in SCENARIOS:
            raise CrossfieldError(f"--scenario: unknown scenario {scenario!r}; scenarios: {', '.join(SCENARIOS)}")
        truth = station_calibration()
        config = load_config(None)
        specs = {
            stage: {"plugin": config.stages[stage].plugin, "options": dict(config.stages[stage].options)}
            for stage in ("centroid", "triangulate")
        }
        frames = simulate_positions(truth, bar_mm, args.frames, args.seed, scenario)
        sizes = (truth.upper.image_size, truth.lower.image_size)
        source = f"crossfield verify --scenario {scenario} --frames {args.frames} --seed {args.seed}"
    calibration = read_stereo_calibration(args.calibration, image_sizes=sizes)
    stages = create_stages(specs, args.recording or "the config")
    result = evaluate(
        frames,
        calibration,
        stages["centroid"],
        stages["triangulate"],
        certified_mm=bar_mm,
        certified_u_mm=bar_u_mm,
        mpe_mm=mpe,
    )
    print(
        f"length verification, scale bar {bar_mm:g} mm (u {bar_u_mm * 1000:g} um), "
        f"MPE {mpe * 1000:g} um, calibration {args.calibration}"
        + (f", pairs from {args.recording}" if args.recording else "")
    )
    for p in result.positions:
        print(
            f"  {p.name:<20} {p.length_mm:10.4f} mm  E {p.error_mm * 1000:+7.1f} um  {'pass' if p.passed else 'FAIL'}"
        )
    print(f"max |E| = {result.max_abs_error_mm * 1000:.1f} um: {verdict_word(result.passed)}")
    text = Path(args.calibration).read_text(encoding="utf-8", errors="replace")
    sealed = None
    if args.record:  # recorded first, so that the verification record states its seal
        sealed = record_verification(args.record, frames, result, text, specs, source, signing_key=args.signing_key)
        print(f"  recorded to {args.record} (chain head {sealed.chain_head}{_signed(sealed)})")
    for path in write_verification(result, args.output, calibration_sha256=hashlib.sha256(text.encode()).hexdigest(),
                                   seal=sealed, operator=args.operator):
        print(f"  report: {path}")
    return 0 if result.passed else 1


COMMANDS: tuple[Command, ...] = (
    Command(
        "calibrate", add_calibrate_arguments, cmd_calibrate,
        help="stereo-calibrate the upper/lower pair from views of a planar board (Zhang), write CALIB.yml",
        description="Zhang stereo calibration from image pairs of a planar board (ChArUco, chessboard or asymmetric "
        "circles), from simulated views (--scenario), or from live cameras (--source). Writes the OpenCV FileStorage YAML the folder, basler and "
        "opencv sources read (M1 D1 M2 D2 R T, image size) with standard deviations under std_* keys, and a report "
        "(<CALIB>-report.html/.json). Exit status 0 on success, 2 if the views cannot give a calibration.",
    ),
    Command(
        "verify", add_verify_arguments, cmd_verify,
        help="VDI/VDE 2634-1 length test: a scale bar in >= 7 positions, length errors E against the MPE",
        description="Acceptance / re-verification of the stereo station in the manner of VDI/VDE 2634 Part 1: a "
        "scale bar with two targets and a certified length is measured in at least 7 positions and orientations "
        "across the measuring volume; per position the length measurement error E = measured - certified; the "
        "station passes if every |E| <= MPE. Writes <OUT>.json/.html (plot). Exit status 0 pass, 1 fail.",
    ),
)

"""``ballbeam``: the command line. Every subcommand takes a config and ``--set`` overrides.

Errors a user can cause print one line and exit 2; nothing prints a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ballbeam.errors import BallbeamError
from ballbeam.runtime.exit_codes import HELP as EXIT_CODES_HELP
from ballbeam.runtime.process import (
    add_config_arguments,
    add_secret_argument,
    config_from_arguments,
    configure_logging,
    resolve_config_argument,
)
from ballbeam.runtime.stop import INTERRUPT

EXIT_USAGE = 2


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 1..65535, got {value}")
    return value


def _live_port(args: argparse.Namespace) -> int | None:
    """The live view's port, or None without --live."""
    from ballbeam.errors import ConfigError
    from ballbeam.runtime.live import DEFAULT_LIVE_PORT

    if not args.live:
        if args.live_port is not None:
            raise ConfigError("--live-port needs --live")
        return None
    return int(args.live_port) if args.live_port is not None else DEFAULT_LIVE_PORT


def _add_live_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--live", action="store_true",
        help="serve the run's channels live over Foxglove's WebSocket protocol (loopback only)",
    )
    parser.add_argument(
        "--live-port", type=_port, default=None, metavar="PORT",
        help="the live view's port on 127.0.0.1 (default: 8765, the Foxglove app's default)",
    )


def _json_ready(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _json_ready(item) for key, item in value.items()}
    return value


def print_json(payload: dict[str, Any]) -> None:
    print(json.dumps(_json_ready(payload), indent=2, sort_keys=True))


def _format_value(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def print_table(title: str, rows: dict[str, Any]) -> None:
    print(title)
    width = max(len(key) for key in rows)
    for key, value in rows.items():
        print(f"  {key:<{width}}  {_format_value(value)}")


def command_plan(args: argparse.Namespace) -> int:
    from ballbeam.assembly import make_plan

    config = config_from_arguments(args)
    plan = make_plan(config)
    summary: dict[str, Any] = {"kind": plan.kind, "duration_s": plan.duration_s}
    summary.update(getattr(plan, "summary", dict)())
    if args.json:
        print_json(summary)
    else:
        print_table(f"plan ({plan.kind})", summary)
    return 0


def command_simulate(args: argparse.Namespace) -> int:
    from ballbeam.assembly import run_offline
    from ballbeam.evaluation.plots import plot_run
    from ballbeam.files import check_new_outputs

    config = config_from_arguments(args)
    check_new_outputs([args.plot])  # before the simulation, not after
    result = run_offline(config)
    metrics = result.metrics.as_dict()
    if args.plot:
        trace = result.trace
        plot_run(
            args.plot,
            trace.time_s,
            trace.true_states,
            trace.reference_states,
            trace.voltage_v,
            config.limits.theta_rad,
            title=f"offline closed loop, {config.plan.kind} path",
        )
    design = result.design
    if args.json:
        print_json(
            {
                "plan_kind": config.plan.kind,
                **({"plan_duration_s": design.plan_duration_s} if design is not None
                   else {"controller_kind": config.controller.kind}),
                **metrics,
            }
        )
    else:
        print_table(
            f"offline simulation ({config.plan.kind} path, "
            f"{design.plan_duration_s:.4f} s plan)" if design is not None
            else f"offline simulation ({config.controller.kind} controller)",
            metrics,
        )
    return 0


def command_daemon(args: argparse.Namespace) -> int:
    from ballbeam.files import remove_if_empty
    from ballbeam.runtime.bus import check_before_start
    from ballbeam.runtime.daemon.loop import PlantLostError
    from ballbeam.runtime.daemon.node import run_daemon
    from ballbeam.runtime.exit_codes import EXIT_PLANT_LOST, exit_code
    from ballbeam.runtime.process import (
        forbid_core_dumps,
        log_from_arguments,
        secret_from_arguments,
    )

    forbid_core_dumps()  # before the key is read: a core would hold it (runtime/process.py)
    configure_logging()
    config = config_from_arguments(args)
    check_before_start(config.bus)  # before the log is made
    live_port = _live_port(args)
    secret = secret_from_arguments(args)
    log_path, log_stream = log_from_arguments(args, config)
    try:
        end_reason = run_daemon(config, log_path, args.config, live_port=live_port, secret=secret,
                                log_stream=log_stream)
    except PlantLostError as error:
        print(f"ballbeam: error: {error}", file=sys.stderr)
        return EXIT_PLANT_LOST
    except BaseException:
        if log_stream is not None:
            remove_if_empty(log_path)  # made for this run, which never began to record
        raise
    finally:
        if secret is not None:
            secret.wipe()
    print(log_path)
    code = exit_code(end_reason)
    if code:
        print(f"ballbeam: the run ended with {end_reason}: exit {code} (log: {log_path})",
              file=sys.stderr)
    return code


def command_emulator(args: argparse.Namespace) -> int:
    from ballbeam.runtime.bus import check_before_start
    from ballbeam.runtime.process import forbid_core_dumps, secret_from_arguments
    from ballbeam_emulator.main import run_emulator

    forbid_core_dumps()  # before the key is read: a core would hold it (runtime/process.py)
    configure_logging()
    config = config_from_arguments(args)
    check_before_start(config.bus)
    secret = secret_from_arguments(args)
    try:
        run_emulator(config, secret)
    finally:
        if secret is not None:
            secret.wipe()
    return 0


def command_run(args: argparse.Namespace) -> int:
    from ballbeam.evaluation.summary import summarise
    from ballbeam.logs.reader import read_log
    from ballbeam.runtime.exit_codes import exit_code
    from ballbeam.runtime.launcher import launch_run

    result = launch_run(args.config, args.overrides, live_port=_live_port(args))
    summary = summarise(read_log(result.log_path), result.config.limits.theta_rad)
    summary = {
        "mode": result.config.run.mode,
        "plan_kind": result.config.plan.kind,
        "wall_time_s": result.wall_time_s,
        "bus": f"{result.config.bus.interface}:{result.config.bus.channel}",
        **({"bus_choice": result.bus_choice} if result.bus_choice else {}),
        **summary,
        "log_path": str(result.log_path),
    }
    if args.json:
        print_json(summary)
    else:
        print_table(
            f"bus run ({result.config.run.mode}, {result.config.plan.kind} path) "
            f"over {result.config.bus.interface}",
            summary,
        )
    end_reason = str(summary.get("end_reason"))
    bound_deg = result.config.limits.theta_deg + result.config.controller.bound_tolerance_deg
    bound_broken = float(summary.get("max_abs_theta_deg") or 0.0) > bound_deg
    code = exit_code(end_reason, bound_broken)
    if code:
        print(
            f"ballbeam: the run ended with {end_reason}"
            + (f" and |θ| reached {summary.get('max_abs_theta_deg')}° (bound "
               f"{result.config.limits.theta_deg}°)" if bound_broken else "")
            + f": exit {code} (log: {result.log_path})"
            + (f"; {summary['late_samples']} sensor samples were read periods late: the "
               "daemon was short of CPU (README: real-time scheduling)"
               if end_reason == "plant_lost" and summary.get("late_samples") else ""),
            file=sys.stderr,
        )
    return code


def _read_log_or_fail(path: str) -> Any:
    from ballbeam.errors import LogFormatError
    from ballbeam.logs.reader import read_log

    try:
        return read_log(path)
    except IsADirectoryError as error:
        raise LogFormatError(f"{path} is a directory, not a log file") from error
    except OSError as error:
        raise LogFormatError(f"cannot open log {path}: {error.strerror or error}") from error


def command_recover(args: argparse.Namespace) -> int:
    from ballbeam.errors import LogFormatError, OutputExistsError
    from ballbeam.files import exists_message
    from ballbeam.logs.recover import recover_log, recovered_path

    source = Path(args.log)
    destination = Path(args.output) if args.output else recovered_path(source)
    if os.path.lexists(destination):
        raise OutputExistsError(f"{exists_message(destination)}; name another with --output")
    try:
        recovery = recover_log(source, destination)
    except OutputExistsError as error:  # it appeared while recovering
        raise OutputExistsError(f"{error}; name another with --output") from error
    except FileNotFoundError as error:
        if not source.exists():
            raise LogFormatError(f"cannot open log {source}: not found") from error
        raise LogFormatError(
            f"cannot write {destination}: {error.strerror or error} ({error.filename})"
        ) from error
    except OSError as error:
        raise LogFormatError(f"cannot recover {source}: {error.strerror or error}") from error
    if recovery.refused is not None:
        # Hostile, not a cut: an error, after what came before it was kept.
        raise LogFormatError(
            f"{source}: {recovery.refused}; the {recovery.messages} messages before it are "
            f"recovered in {destination}"
        )
    report = {
        "source": str(recovery.source),
        "recovered": str(recovery.destination),
        "was_complete": recovery.was_complete,
        "stopped_because": recovery.stopped_because or "-",
        "messages": recovery.messages,
        "attachments": recovery.attachments,
        "metadata": recovery.metadata,
        "last_log_time_ns": recovery.last_log_time_ns,
    }
    if args.json:
        print_json(report)
    else:
        print_table("recovered log", report)
    return 0


def command_replay(args: argparse.Namespace) -> int:
    from ballbeam.evaluation.summary import summarise
    from ballbeam.files import check_new_outputs

    # Before any work: an output that is there already (the log itself above all) is refused.
    check_new_outputs([args.plot, args.report], inputs=[args.log])
    run_log = _read_log_or_fail(args.log)
    summary = summarise(run_log)
    summary["log_path"] = args.log
    exit_code = 0
    if args.verify:
        from ballbeam.evaluation.replay import verify

        result = verify(run_log)
        summary["verify_cycles"] = result.cycles_checked
        summary["verify_ok"] = result.ok
        summary["verify_design"] = result.design_source
        if result.resynthesis_difference is not None:
            # Information, not a verdict: today's synthesis on this machine vs the recorded.
            summary["resynthesis_max_rel_diff"] = result.resynthesis_difference
        if result.mismatch is not None:
            mismatch = result.mismatch
            summary["verify_first_mismatch_cycle"] = mismatch.cycle
            # A re-planning log from before its designs were recorded on /plans re-makes
            # them through this machine's LAPACK (docs/decisions.md, issue 27).
            kernel_note = (
                "; a re-planning log whose /plans carry no designs verifies bit for bit only on"
                " the BLAS kernel it was recorded with"
                if result.design_source == "recorded plans" else ""
            )
            print(
                f"ballbeam: verify FAILED at cycle {mismatch.cycle} (command #{mismatch.index}): "
                f"recorded {mismatch.recorded_v!r} V, replayed {mismatch.replayed_v!r} V"
                f"{kernel_note}",
                file=sys.stderr,
            )
            exit_code = 1
        if result.plan_mismatch is not None:
            summary["verify_plan_mismatch"] = result.plan_mismatch
            print(f"ballbeam: verify FAILED: {result.plan_mismatch}", file=sys.stderr)
            exit_code = 1
    if args.plot:
        from ballbeam.evaluation.plots import plot_log

        plot_log(args.plot, run_log, title=f"replay of {args.log}")
    if args.report:
        from ballbeam.evaluation.report import write_report

        write_report(run_log, summary, args.report)
    foxglove_steps = None
    if args.foxglove:
        from ballbeam.errors import LogFormatError
        from ballbeam.evaluation.foxglove import how_to_open

        try:
            foxglove_steps = how_to_open(args.log)
        except OSError as error:
            raise LogFormatError(
                f"cannot write the Foxglove layout next to {args.log}: "
                f"{error.strerror or error}"
            ) from error
    if args.json:
        print_json(summary)
    else:
        if run_log.truncated:
            print(
                f"note: the log was cut short ({run_log.truncation_reason}); "
                f"read up to {summary['last_time_s']:.3f} s"
            )
        print_table(f"replay of {args.log}", summary)
    if foxglove_steps is not None:
        # After the figures; on stderr with --json, so that stdout stays one JSON object.
        print(foxglove_steps, file=sys.stderr if args.json else sys.stdout)
    return exit_code


def command_regress(args: argparse.Namespace) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from ballbeam.evaluation import regress
    from ballbeam.files import check_new_outputs

    check_new_outputs([args.junit_xml])  # before the scenarios run, not after
    paths = regress.discover(args.scenarios)
    with tqdm(total=len(paths), unit="scenario", file=sys.stderr, disable=args.json) as bar:

        def done(result: regress.ScenarioResult) -> None:
            bar.set_postfix_str(f"{result.name}: {'pass' if result.passed else 'FAIL'}")
            bar.update()

        jobs = args.jobs or regress.default_jobs()
        results = regress.run_all(paths, jobs, args.overrides, on_done=done)
    if args.junit_xml:
        regress.write_junit(results, Path(args.junit_xml))
    if args.json:
        print_json(regress.as_json(results))
    else:
        print(regress.table(results))
    return 0 if all(result.passed for result in results) else 1


def _scheduler_address(text: str) -> str:
    if not text.startswith(("tcp://", "tls://", "inproc://", "ucx://")) or len(text) < 8:
        raise argparse.ArgumentTypeError(
            f"not a Dask scheduler address (tcp://HOST:PORT): {text!r}"
        )
    return text


def _resume_command(command: str, args: argparse.Namespace, output: Path,
                    *extra: str) -> str:
    """The command line that takes an interrupted study up again where it stopped: the same
    spec (as a path that works from anywhere, or the shipped name given), output, cluster."""
    import shlex

    spec = Path(args.spec)
    argv = ["ballbeam", command, str(spec.absolute()) if spec.exists() else args.spec,
            "--output", str(output.absolute()), *extra]
    if args.scheduler:
        argv += ["--scheduler", args.scheduler]
    if args.workers:
        argv += ["--workers", str(args.workers)]
    return shlex.join(argv)


def command_sweep(args: argparse.Namespace) -> int:
    from ballbeam.studies.cluster import dask_client, import_studies_extra
    from ballbeam.studies.engine import metric_columns, run_sweep, stored_points
    from ballbeam.studies.report import failures_text, plot_sweep, summary_text
    from ballbeam.studies.spec import load_spec

    spec = load_spec(args.spec)
    import_studies_extra()
    output = Path(args.output) if args.output else (
        spec.output or Path("sweep-results") / spec.path.stem
    )
    INTERRUPT.install()
    try:
        outcome = run_sweep(
            spec,
            output,
            lambda: dask_client(args.scheduler, args.workers),
            retry_failed=args.retry_failed,
            progress=not args.json,
        )
    except KeyboardInterrupt:
        kept, total = stored_points(spec, output)
        print(f"\nballbeam: sweep interrupted: {kept} of {total} points are saved in "
              f"{(output / 'points').absolute()}; resume with: "
              f"{_resume_command('sweep', args, output)}", file=sys.stderr)
        return 130
    metrics = metric_columns(outcome.table, spec)
    plots = [] if args.no_plots else plot_sweep(outcome.table, spec, metrics, output / "plots")
    report = {
        "spec": str(spec.path),
        "runner": spec.runner,
        "points": outcome.total,
        "ran": outcome.ran,
        "skipped_done": outcome.skipped,
        "failed": outcome.failed,
        "workers": outcome.workers,
        "wall_time_s": outcome.wall_time_s,
        "table": str(outcome.table_path),
        "plots": [str(path) for path in plots],
    }
    if args.json:
        print_json(report)
        return 0
    print(summary_text(outcome.table, metrics, title=(
        f"sweep {spec.path.stem} ({spec.runner}): {outcome.total} points, {outcome.ran} run "
        f"now, {outcome.skipped} already done, {outcome.failed} failed; "
        f"{outcome.wall_time_s:.1f} s on {outcome.workers} worker(s)"
    )))
    failures = failures_text(outcome.table)
    if failures:
        print(failures)
    print(f"table: {outcome.table_path}")
    if plots:
        print(f"plots: {plots[0].parent}/ ({len(plots)} files)")
    return 0


def command_tune(args: argparse.Namespace) -> int:
    from ballbeam.studies.cluster import dask_client, import_studies_extra
    from ballbeam.studies.tune import (
        STUDY_FILE,
        completed_trials,
        load_tune_spec,
        markdown_table,
        run_tune,
    )

    spec = load_tune_spec(args.spec)
    if args.trials is not None:
        spec = dataclasses.replace(spec, trials=args.trials)
    import_studies_extra()
    output = Path(args.output) if args.output else (
        spec.output or Path("sweep-results") / spec.path.stem
    )
    INTERRUPT.install()
    try:
        with dask_client(args.scheduler, args.workers) as client:
            outcome = run_tune(spec, output, client, progress=not args.json)
    except KeyboardInterrupt:
        trials = ["--trials", str(args.trials)] if args.trials is not None else []
        print(f"\nballbeam: tune interrupted: {completed_trials(output)} of {spec.trials} "
              f"trials are saved in {(output / STUDY_FILE).absolute()}; resume with: "
              f"{_resume_command('tune', args, output, *trials)}", file=sys.stderr)
        return 130
    report = {
        "spec": str(spec.path),
        "trials": spec.trials,
        "best_trial": outcome.best_trial,
        "default": outcome.default_params,
        "tuned": outcome.best_params,
        "tuned_config": str(outcome.tuned_path),
        "holdout_worst_improvement": outcome.holdout_improvement,
        "before_after": outcome.table,
    }
    if args.json:
        print_json(report)
        return 0
    print(f"tuned in {spec.trials} trials (best: trial {outcome.best_trial}); "
          f"{spec.objective} {spec.metric} over {len(spec.train.points())} tuning runs, "
          f"verdict on {len(spec.holdout.points())} held-out runs")
    print(markdown_table(outcome.table))
    print(f"held-out worst {spec.metric}: {100 * outcome.holdout_improvement:+.1f} % "
          "better than the default" if outcome.holdout_improvement >= 0 else
          f"held-out worst {spec.metric}: {100 * -outcome.holdout_improvement:.1f} % worse "
          "than the default")
    print(f"tuned config: {outcome.tuned_path}")
    return 0


def command_bus(args: argparse.Namespace) -> int:
    """``bus setup``: make the vcan interfaces runs use (root), or print the commands;
    ``bus status``: where a run's ``auto`` bus goes now."""
    import os
    import shlex

    from ballbeam.config import BusSection
    from ballbeam.runtime.bus import (
        can_interfaces,
        resolve_auto,
        run_setup,
        setup_commands,
        socketcan_available,
    )

    if args.action == "status":
        choice = resolve_auto(BusSection(), claim=False)
        print(f"auto: {choice.interface} {choice.channel} ({choice.reason})")
        return 0
    commands = setup_commands(args.count, not args.classic, can_interfaces(), args.prefix)
    if not commands:
        print(f"ballbeam: {args.count} vcan interface(s) already up", file=sys.stderr)
        return 0
    if os.geteuid() != 0:
        print("ballbeam: not root; as root, run:", file=sys.stderr)
        for command in commands:
            print(shlex.join(command))
        return 0
    run_setup(commands)
    if not socketcan_available():
        print("ballbeam: the vcan interfaces exist, but this kernel refuses CAN sockets "
              "(can-raw): runs go over udp_multicast", file=sys.stderr)
        return EXIT_USAGE
    for found in can_interfaces():
        if found.virtual and found.name.startswith(args.prefix):
            print(f"{found.name}: {'CAN FD' if found.fd else 'classic'} (MTU {found.mtu}), "
                  f"{'up' if found.up else 'down'}")
    return 0


def command_configs(args: argparse.Namespace) -> int:
    from ballbeam.config import resolve_config_path, shipped_configs

    root = shipped_configs()
    if args.name:
        path = resolve_config_path(args.name)
        print(path.read_text(encoding="utf-8"), end="")
        return 0
    print(f"shipped configs ({root}):")
    for path in sorted(root.rglob("*.toml")):
        lines = path.read_text(encoding="utf-8").splitlines()
        about = next((line.lstrip("# ").strip() for line in lines if line.startswith("#")), "")
        print(f"  {path.relative_to(root).with_suffix('')!s:36} {about}")
    return 0


def _add_cluster_arguments(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--scheduler", type=_scheduler_address, metavar="tcp://HOST:PORT",
        help="run on this Dask cluster (default: an embedded LocalCluster on 127.0.0.1)",
    )
    where.add_argument(
        "--workers", type=_positive_int, default=None,
        help="worker processes of the embedded cluster (default: one per core)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ballbeam",
        description="Optimal tracking controller bench for the SRV02 ball-and-beam.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    plan = commands.add_parser("plan", help="plan the path and print its duration and summary")
    add_config_arguments(plan)
    plan.add_argument("--json", action="store_true", help="print one JSON object")
    plan.set_defaults(handler=command_plan)

    simulate = commands.add_parser("simulate", help="run the offline closed loop (no bus)")
    add_config_arguments(simulate)
    simulate.add_argument("--json", action="store_true", help="print one JSON object")
    simulate.add_argument("--plot", metavar="PNG", help="write a paper-style figure")
    simulate.set_defaults(handler=command_simulate)

    run = commands.add_parser(
        "run", help="run emulator and daemon as two processes over the bus, record, summarise",
        epilog=EXIT_CODES_HELP,
    )
    add_config_arguments(run)
    run.add_argument("--json", action="store_true", help="print one JSON object")
    _add_live_arguments(run)
    run.set_defaults(handler=command_run)

    daemon = commands.add_parser(
        "daemon", help="run the controller daemon alone", epilog=EXIT_CODES_HELP
    )
    add_config_arguments(daemon)
    add_secret_argument(daemon)
    daemon.add_argument(
        "--log", metavar="MCAP",
        help="log file, a new one (default: a new one in run.log_dir); never over a file",
    )
    daemon.add_argument(
        "--log-fd", type=int, metavar="N",
        help="record to the new, empty file open on descriptor N, named by --log (what ballbeam "
        "run passes: it creates the file)",
    )
    _add_live_arguments(daemon)
    daemon.set_defaults(handler=command_daemon)

    replay = commands.add_parser("replay", help="analyse a recorded run; --verify re-runs it")
    replay.add_argument("log", metavar="LOG.mcap")
    replay.add_argument("--json", action="store_true", help="print one JSON object")
    replay.add_argument("--plot", metavar="PNG", help="write a paper-style figure with timing")
    replay.add_argument(
        "--foxglove", action="store_true",
        help="print how to open the log in Foxglove with the shipped layout (written beside it)",
    )
    replay.add_argument(
        "--report", metavar="HTML",
        help="write one self-contained page: metrics, figures, faults, timing, the config",
    )
    replay.add_argument(
        "--verify",
        action="store_true",
        help="re-run the controller on the recorded sensor frames; exit 1 on any difference",
    )
    replay.set_defaults(handler=command_replay)

    recover = commands.add_parser(
        "recover", help="make a log cut short whole again (complete, indexed MCAP)"
    )
    recover.add_argument("log", metavar="LOG.mcap")
    recover.add_argument(
        "-o", "--output", metavar="OUT.mcap",
        help="where to write it (default: LOG.recovered.mcap beside it; never over an existing "
        "file)",
    )
    recover.add_argument("--json", action="store_true", help="print one JSON object")
    recover.set_defaults(handler=command_recover)

    regress_parser = commands.add_parser(
        "regress", help="run every scenario over the bus and check its [expect] bounds"
    )
    regress_parser.add_argument(
        "scenarios",
        nargs="*",
        metavar="SCENARIO",
        help="scenario files or directories, on disk or shipped (default: every shipped one)",
    )
    regress_parser.add_argument(
        "--jobs", type=_positive_int, default=None, help="scenarios at once (default: one per core)"
    )
    regress_parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a key in every scenario",
    )
    regress_parser.add_argument("--json", action="store_true", help="print one JSON object")
    regress_parser.add_argument("--junit-xml", metavar="PATH", help="write a JUnit XML report")
    regress_parser.set_defaults(handler=command_regress)

    sweep = commands.add_parser(
        "sweep", help="a grid and/or Monte-Carlo of runs on a Dask cluster: table and plots"
    )
    sweep.add_argument("spec", metavar="SPEC.toml", help="sweep spec (or a shipped one, "
                       "e.g. sweeps/mismatch_monte_carlo)")
    sweep.add_argument("--output", metavar="DIR", help="results directory (default: the "
                       "spec's sweep.output, else sweep-results/<spec name>)")
    _add_cluster_arguments(sweep)
    sweep.add_argument("--retry-failed", action="store_true",
                       help="run again the points that failed before (done ones are skipped)")
    sweep.add_argument("--no-plots", action="store_true", help="write the table only")
    sweep.add_argument("--json", action="store_true", help="print one JSON object, no bar")
    sweep.set_defaults(handler=command_sweep)

    tune = commands.add_parser(
        "tune", help="choose tracker, observer and plan keys for a robust objective (Optuna)"
    )
    tune.add_argument("spec", metavar="SPEC.toml", help="tuning spec (or a shipped one, "
                      "e.g. sweeps/tune_robust_rest)")
    tune.add_argument("--output", metavar="DIR", help="results directory (default: the spec's "
                      "tune.output, else sweep-results/<spec name>); its study.db keeps the "
                      "trials, and a tuning run again there resumes")
    tune.add_argument("--trials", type=_positive_int, default=None, metavar="N",
                      help="whole trials the study should hold (default: the spec's "
                      "tune.trials); those a stopped tuning left in DIR count, so the same "
                      "command resumes it and a larger N tunes on")
    _add_cluster_arguments(tune)
    tune.add_argument("--json", action="store_true", help="print one JSON object, no bar")
    tune.set_defaults(handler=command_tune)

    bus = commands.add_parser(
        "bus", help="setup: create the vcan interfaces runs use (root; else print the "
        "commands); status: where an auto bus goes"
    )
    bus.add_argument("action", choices=("setup", "status"))
    bus.add_argument(
        "--count", type=_positive_int, default=2,
        help="vcan interfaces, one per run at once (default: 2)",
    )
    bus.add_argument("--prefix", default="vcan", help="interface names (default: vcan0, …)")
    bus.add_argument(
        "--classic", action="store_true",
        help="classic CAN (MTU 16: the 8-byte E2E contract) instead of CAN FD (MTU 72)",
    )
    bus.set_defaults(handler=command_bus)

    configs = commands.add_parser(
        "configs", help="list the configs shipped with the package, or print one"
    )
    configs.add_argument("name", nargs="?", help="a shipped config to print (to copy and edit)")
    configs.set_defaults(handler=command_configs)

    emulator = commands.add_parser("emulator", help="run the plant emulator alone")
    add_config_arguments(emulator)
    add_secret_argument(emulator)
    emulator.set_defaults(handler=command_emulator)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] = args.handler
    try:
        resolve_config_argument(args)
        return handler(args)
    except BallbeamError as error:
        print(f"ballbeam: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (``ballbeam plan | head``): not an error of ours.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())

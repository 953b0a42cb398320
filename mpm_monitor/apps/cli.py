"""Command-line interface: ``python -m mpm_monitor <command>``.

Commands
--------
analyze    offline analysis of a CSV log or a bag
reproduce  simulate a case and print the paper-style result
simulate   run a closed-loop simulation and write the CSV log
demo       run the four ROS 2 nodes in-process on a case
export     write a bag's setpoint, input, output (and disturbance) topics as CSV
recover    rewrite a hard-killed recording as a closed bag

Bad input exits with code 2 and one line on stderr; never a traceback.  The commands, their flags
and the JSON report are described in docs/interfaces.md.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import sys
from pathlib import Path
from typing import Optional

from ..core.errors import InputError


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line and exit code 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


#: The analysis options given on the command line of ``analyze`` and ``reproduce``, in their flags' order.
CLI_ANALYSIS_OPTIONS = ("method", "alpha", "na", "max_na", "nb", "band", "initial_state", "repair", "element_response",
                        "confirm_responses", "release_explained", "release_quiet_rows", "repair_again", "drop_spikes",
                        "max_delay", "max_gap", "jobs")

#: Names of the values of an option that takes several (default: the option's name in capitals).
_METAVARS = {"band": ("LOW", "HIGH")}
#: What a default of None means, for the options that have one.
_NONE_DEFAULTS = {"max_delay": "the model's largest delay + 5, at least 10",
                  "max_gap": "the longest lag of the tests, max_delay + nb",
                  "jobs": "2 where this process may run on two cores or more, else 1"}
#: Options whose command-line default differs from the analysis's (None: chosen when the command runs,
#: :func:`_analysis_options`).  The command uses the machine's second core; the library and the live
#: monitor default to one process.
_CLI_DEFAULTS = {"jobs": None}


def _text(value) -> str:
    if isinstance(value, (tuple, list)):
        return " ".join(_text(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _integer_in_range(low: int, text: str, high: Optional[int] = None) -> int:
    """``text`` as an integer >= ``low`` (and <= ``high`` when given), or argparse's error naming what was expected."""
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < low or (high is not None and value > high):
        expected = f"an integer >= {low}" if high is None else f"an integer in [{low}, {high:,}]"
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def _seed(text: str) -> int:
    """argparse type of ``--seed``: an integer >= 0 (numpy's generators take no negative seed)."""
    return _integer_in_range(0, text)


#: Most samples ``simulate`` and ``reproduce`` run: a million samples of a 3x3 loop take about two minutes and a
#: few hundred MB; 1e12 ran until the machine's memory was gone.
MAX_SIMULATED_SAMPLES = 1_000_000


def _samples(text: str) -> int:
    """argparse type of ``--samples`` of ``simulate`` and ``reproduce``: an integer in [1, MAX_SIMULATED_SAMPLES]."""
    return _integer_in_range(1, text, MAX_SIMULATED_SAMPLES)


def _path(text: str) -> str:
    """argparse type of a file or directory argument: a path that is not empty (an empty one, as
    ``--data "$UNSET"`` gives, would otherwise read as no argument at all or as the current directory)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a file or directory path, got {text!r}")
    return text


def _amplitude(text: str) -> float:
    """argparse type of ``--dither``: a finite number >= 0 (0: no dither), within the analysis's scale (a log
    dithered by 1e300 was written, and every reader refuses it)."""
    from ..core.logged_data import MAX_ANALYSIS_SCALE

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0.0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0 (input units; 0: none), got {text!r}")
    if value > MAX_ANALYSIS_SCALE:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_ANALYSIS_SCALE:g} (input units: a log dithered "
                                         f"beyond it cannot be analysed), got {text!r}")
    return value


def _add_analysis_options(p: argparse.ArgumentParser) -> None:
    """One flag per option of :data:`CLI_ANALYSIS_OPTIONS`, from its ParamSpec (:data:`ANALYSIS_PARAMS`).

    ``--name-with-dashes VALUE``; a choice lists its choices; a ``double_array`` takes its values
    after the flag; a bool that is on by default is turned off by ``--no-name``.  The values are
    checked by :class:`~mpm_monitor.core.analysis.AnalysisOptions` itself.
    """
    from ..core.analysis_options import ANALYSIS_PARAMS

    for name in CLI_ANALYSIS_OPTIONS:
        spec = ANALYSIS_PARAMS[name]
        flag = "--" + name.replace("_", "-")
        what = spec.description.rstrip(".")
        if spec.kind == "bool":
            if spec.default:
                p.add_argument("--no-" + name.replace("_", "-"), dest=name, action="store_false",
                               help=f"turn off (on by default): {what}")
            else:
                p.add_argument(flag, dest=name, action="store_true", help=f"{what} (off by default)")
            continue
        default = _CLI_DEFAULTS.get(name, spec.default)
        shown = _NONE_DEFAULTS.get(name, "None") if default is None else _text(default)
        help_text = f"{what} (default {shown})"
        if spec.choices:
            p.add_argument(flag, dest=name, choices=spec.choices, default=spec.default, help=help_text)
        elif spec.kind == "double_array":
            p.add_argument(flag, dest=name, type=float, nargs=spec.length, default=spec.default,
                           metavar=_METAVARS.get(name, name.upper()), help=help_text)
        else:
            p.add_argument(flag, dest=name, type=int if spec.kind == "int" else float, default=default,
                           help=help_text)


def _analysis_options(args):
    from ..core.analysis import AnalysisOptions
    from ..core.parallel import default_jobs

    values = {name: getattr(args, name) for name in CLI_ANALYSIS_OPTIONS}
    if values["jobs"] is None:
        values["jobs"] = default_jobs()
    return AnalysisOptions(**values)


def _add_topics(p: argparse.ArgumentParser) -> None:
    """``--topics SETPOINT INPUT OUTPUT [DISTURBANCE]`` (checked by :func:`_topics`)."""
    p.add_argument("--topics", nargs="+", metavar="TOPIC", default=None,
                   help="topic names in the bag: SETPOINT INPUT OUTPUT [DISTURBANCE] (default setpoint input output, "
                        "and disturbance when measured disturbances are read)")


def _topics(args) -> tuple:
    """The topics of ``--topics`` (three or four names), or the defaults."""
    from ..io.bags import DEFAULT_TOPICS

    if args.topics is None:
        return DEFAULT_TOPICS
    if len(args.topics) not in (3, 4):
        raise InputError(f"--topics: expected three topic names (SETPOINT INPUT OUTPUT) or four (and DISTURBANCE), "
                         f"got {len(args.topics)}")
    return tuple(args.topics)


#: The simulation cases of ``reproduce``, ``simulate`` and ``demo`` (:data:`mpm_monitor.sim.cases.DEMO_CASES`,
#: spelled out so that the parser does not import the simulation).
DEMO_CASES = ("3.1", "3.2", "3.3", "level")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="python -m mpm_monitor", description="Model-plant mismatch monitor for MPC loops.")
    sub = parser.add_subparsers(dest="command", parser_class=_Parser)

    p = sub.add_parser("analyze", help="analyse a CSV log or a bag against a model")
    p.add_argument("--model", type=_path, required=True, help="model file (YAML)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=_path, help="logged data (CSV; gzip-compressed too; '-' = standard input)")
    src.add_argument("--bag", type=_path, help="rosbag2 directory with the setpoint, input and output topics (and the "
                     "disturbance topic for a model with measured disturbances)")
    p.add_argument("--json", type=_path, dest="json_out", help="write the JSON report to this file ('-' = stdout)")
    p.add_argument("--repair-out", type=_path, help="write the repaired model file (YAML) here")
    p.add_argument("--report", type=_path, help="write an HTML report with figures into this directory")
    p.add_argument("--candidates", metavar="all|NAME[,NAME...]", default=None,
                   help="logged channels the model does not use (CSV columns), tested as causes of each output's "
                        "prediction error; a located one is added to the repaired model as a measured disturbance "
                        "('all': every numeric column the model does not use)")
    _add_bad_values(p, "a sample with an empty, non-numeric or non-finite value of the model's channels (a "
                       "historian's missing value): refuse the log, naming its line and column, or leave the sample "
                       "out as a gap the analysis goes around, with a warning that counts them (default: refuse)")
    _add_topics(p)
    _add_hold_setpoint(p)
    _add_analysis_options(p)

    p = sub.add_parser("reproduce", help="simulate a case and print the paper-style result")
    p.add_argument("--case", choices=DEMO_CASES, required=True)
    p.add_argument("--samples", type=_samples, default=3000)
    p.add_argument("--seed", type=_seed, default=1)
    p.add_argument("--plots", type=_path, default="reproduce_plots", help="directory for the singular-value PNGs")
    _add_analysis_options(p)

    p = sub.add_parser("simulate", help="run a closed-loop simulation and write the CSV log")
    p.add_argument("--case", choices=DEMO_CASES, default=None,
                   help="a case (plant and model): the paper's 3.1, 3.2, 3.3, or level")
    p.add_argument("--plant", type=_path, help="plant model file (YAML); with --model instead of --case")
    p.add_argument("--model", type=_path, help="controller model file (YAML)")
    p.add_argument("--samples", type=_samples, default=3000)
    p.add_argument("--seed", type=_seed, default=1)
    p.add_argument("--dither", type=_amplitude, default=None,
                   help="amplitude of a PRBS dither on every input (default 0: none)")
    p.add_argument("--experiment", type=_path, default=None, metavar="REPORT_JSON",
                   help="add the dither of the experiment an analyze --json report recommends (its amplitude per "
                        "input, switching with probability 1/2); instead of --dither")
    p.add_argument("--csv", type=_path, required=True, help="output CSV file")
    p.add_argument("--write-model", type=_path, help="also write the controller model file here")

    p = sub.add_parser("demo", help="run the ROS 2 nodes in-process on a case")
    p.add_argument("--case", choices=DEMO_CASES, default="3.2",
                   help="the paper's 3.1, 3.2, 3.3, or level (an integrating level and a measured inflow)")
    p.add_argument("--samples", type=int, default=None, help="samples to simulate (default: the case's)")
    p.add_argument("--bag", type=_path, default=None, help="record every topic to this rosbag2 (MCAP) directory")
    p.add_argument("--seed", type=_seed, default=1)
    p.add_argument("--quiet", action="store_true", help="print only the final result")

    p = sub.add_parser("export", help="write a bag's setpoint, input, output (and disturbance) topics as a CSV log")
    p.add_argument("--bag", type=_path, required=True)
    p.add_argument("--csv", type=_path, required=True)
    p.add_argument("--model", type=_path, default=None, help="model file giving channel order and sample time (optional)")
    _add_bad_values(p, "a message holding a non-finite value: refuse the bag, naming the topic, message and stamp, "
                       "or leave its sample out of the CSV (t skips it), with a warning that counts them "
                       "(default: refuse)")
    _add_topics(p)
    _add_hold_setpoint(p)

    p = sub.add_parser("recover", help="rewrite a hard-killed recording (no metadata.yaml) as a closed bag")
    p.add_argument("--bag", type=_path, required=True, help="the unclosed bag directory")
    p.add_argument("--out", type=_path, required=True, help="new bag directory (must not exist)")
    return parser


def _add_hold_setpoint(p) -> None:
    p.add_argument("--hold-setpoint", action="store_true",
                   help="a --bag of a stack that publishes its setpoints only on change (the monitor's hold_setpoint): "
                        "every sample takes the latest setpoint stamped at or before it")


def _add_bad_values(p, help_text: str) -> None:
    p.add_argument("--bad-values", choices=("refuse", "gap"), default="refuse", help=help_text)


def _cmd_recover(args) -> int:
    from ..io.bags import recover_bag

    _refuse_dash(args.out, "--out", "a directory to write the recovered bag into",      # a directory "-" was made
                 "standard output is not supported for --out")
    _not_an_input(args.out, "--out", {"--bag": args.bag})       # as export --csv (the recovered bag in the damaged one)
    n = recover_bag(args.bag, args.out, warn=lambda note: print(f"warning: {note}", file=sys.stderr))
    _say(f"recovered {n} messages into {args.out}")
    return 0


def _cmd_analyze(args) -> int:
    if args.data == "-":
        args.data = "/dev/stdin"        # named so in messages and in the report's source
    _refuse_dash(args.repair_out, "--repair-out", "a file to write the repaired model to",   # a file "-" was written
                 "standard output holds the summary, or the JSON report with --json -")
    for path, what in ((args.json_out, "--json"), (args.repair_out, "--repair-out")):
        if path and path != "-":
            # The repaired model may replace the model file (an update in place); nothing may replace the log.
            _not_an_input(path, what, {"--data": args.data, "--bag": args.bag,
                                       **({"--model": args.model} if what == "--json" else {})})
            _check_output_file(path, what)
    if args.report:
        _check_output_directory(args.report, "--report")
        _report_apart(args)
    if args.data is not None and args.topics is not None:
        raise InputError("--topics: names the topics of a --bag; a --data CSV names its channels in its header")
    if args.data is not None and args.hold_setpoint:
        raise InputError("--hold-setpoint: reads the setpoints of a --bag; a --data CSV has a setpoint in every row")
    if args.repair_out and args.repair_out != "-" and not getattr(args, "repair", True):
        raise InputError(f"--repair-out {args.repair_out}: there is no repaired model with --no-repair (it wrote the "
                         f"model as given): leave out one of the two")
    _distinct_outputs((("--json", args.json_out), ("--repair-out", args.repair_out), ("--report", args.report)))
    # One analysis, then the process ends: the cyclic garbage collector only costs time here (its passes
    # over the objects of the imports and the analysis: 27 ms at 20x20 and 56 ms at 100x40 by its own
    # callbacks), while what the analysis frees is freed by reference counting (the peak memory stays the
    # same).  The long-running monitor keeps it.
    collecting = gc.isenabled()
    gc.disable()
    try:
        if not args.data:
            return _analyze(args, None)
        # The CSV's C parse runs in a child process while this one imports the analysis and loads the model.
        from ..io.csv_log import start_csv_read

        started = start_csv_read(args.data)
        try:
            return _analyze(args, started)
        finally:
            started.close()
    finally:
        if collecting:
            gc.enable()


def _analyze(args, started) -> int:
    """``analyze`` once its output files are checked; ``started``: the CSV's read (:func:`start_csv_read`)."""
    from ..core.logged_data import NUMERICAL_ERRORS, check_scale
    from ..core.pipeline import analyze
    from ..io.csv_log import read_csv
    from ..io.model_file import load_model, save_model

    model = load_model(args.model)
    options = _analysis_options(args)
    if args.data:
        if started is not None:                   # while the child parses the CSV
            from ..core.analysis import load_tests

            load_tests(model)
        data = read_csv(args.data, model, started=started, bad_values=args.bad_values)
    else:
        from ..io.bags import read_bag

        data = read_bag(args.bag, model, topics=_topics(args), progress=sys.stderr.isatty(),
                        bad_values=args.bad_values, hold_setpoint=args.hold_setpoint)
    check_scale(model, data, model_source=args.model)
    candidates = None
    if args.candidates is not None:
        from ..core.candidates import select_candidates

        candidates = select_candidates(data, args.candidates, model)
    try:
        report = analyze(model, data, options) if candidates is None else \
            analyze(model, data, options, candidates=candidates)
    except (*NUMERICAL_ERRORS, InputError) as exc:  # backstop of check_scale
        from ..core.logged_data import divergence_warnings

        cause = exc.__cause__ if isinstance(exc, InputError) else exc  # analyze raises numerical_breakdown
        if not isinstance(cause, NUMERICAL_ERRORS):
            raise
        diverging = divergence_warnings(model.outputs, data.y)
        why = diverging[0] if diverging else "values or model parameters too large or degenerate?"
        raise InputError(f"{data.source}: the analysis broke down numerically with model {args.model} "
                         f"({_one_line(cause)}): {why}") from None
    from ..io.json_text import dumps_indented     # json.dumps(..., indent=2)'s text, quicker

    if args.json_out == "-":
        _say(dumps_indented(report.to_dict()))
    else:
        if args.json_out:
            text = dumps_indented(report.to_dict()) + "\n"
            from ..io.files import write_text_replacing

            _write_output(args.json_out, "--json", lambda: write_text_replacing(args.json_out, text))
        _say(report.summary_text())
    if args.repair_out:
        _write_output(args.repair_out, "--repair-out", lambda: save_model(report.repaired_model, args.repair_out))
    if args.report:
        from ..io.report import write_report

        write_report(args.report, model, data, report)
    return 0


def _check_output_file(path: str, flag: str) -> None:
    """Refuse, before any work, an output file that cannot be written (a directory, a missing or
    read-only directory, a read-only file): one line naming the flag and the path.

    Raises
    ------
    InputError
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{flag} {path}: is a directory: expected the path of a file to write")
    parent = p.parent
    if not parent.is_dir():
        if parent.exists():
            raise InputError(f"{flag} {path}: {parent} is a file, not a directory")
        raise InputError(f"{flag} {path}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise InputError(f"{flag} {path}: not writable")
    if not p.exists():
        _probe_directory(parent, flag, path)


def _check_output_directory(path: str, flag: str) -> None:
    """Refuse, before any work, a directory to write into that cannot be made or written (a file of that
    name, a file on its way, a read-only ancestor): one line naming the flag and the path.  A directory
    that does not exist yet is made later, with its missing parents.

    Raises
    ------
    InputError
    """
    _refuse_dash(path, flag, "a directory to write into", f"standard output is not supported for {flag}")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{flag} {path}: is a file: expected a directory to write into")
    ancestor = p
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise InputError(f"{flag} {path}: {ancestor} is a file, not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {path}: {ancestor} is not writable")
    _probe_directory(ancestor, flag, path)


def _probe_directory(directory: Path, flag: str, path: str) -> None:
    """Create and remove a file in ``directory``, the test ``os.access`` cannot make: it grants root
    every directory, also those of sysfs or procfs, where nothing can be created.

    Raises
    ------
    InputError
        Naming the flag, the path and the directory.
    """
    import tempfile

    try:
        fd, name = tempfile.mkstemp(prefix=".mpm_monitor_probe_", dir=directory)
    except OSError as exc:
        raise InputError(f"{flag} {path}: {directory} is not writable: {exc.strerror or _one_line(exc)}") from None
    os.close(fd)
    os.unlink(name)


def _write_output(path: str, flag: str, write) -> None:
    """Call ``write()``, turning an OS error (disk full, permissions changed since the check) into one line."""
    try:
        write()
    except OSError as exc:
        raise InputError(f"{flag} {path}: cannot write: {exc.strerror or _one_line(exc)}") from None


class _StandardOutputError(Exception):
    """Writing to the standard output failed for another reason than a closed reader (a full disk, an I/O error
    of the file or device it was sent to); :func:`main` says so in one line.

    Parameters
    ----------
    cause : OSError
        The error of the write.
    """

    def __init__(self, cause: OSError):
        super().__init__(cause.strerror or _one_line(cause))
        self.cause = cause


def _say(text: str) -> None:
    """Write ``text`` and a newline to the standard output and flush it, so that a write that fails does so here
    (rather than in the flush at exit, where it could only be ignored).

    Raises
    ------
    _StandardOutputError
        When the write fails (a full disk: ``> /dev/full``).
    BrokenPipeError
        When the reader went away (``| head``), as before.
    """
    _CheckedStandardOutput.write(text + "\n")


class _CheckedStandardOutput:
    """The standard output as a stream whose every write is flushed and checked (:func:`_say`): what ``demo``
    writes to (a full disk gave a traceback and exit 1)."""

    @staticmethod
    def write(text: str) -> None:
        if sys.stdout is None:      # started with the standard output closed (>&-): nothing to write to, as print()
            return
        try:
            sys.stdout.write(text)
            sys.stdout.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise _StandardOutputError(exc) from None

    @staticmethod
    def flush() -> None:
        """Nothing: every write was flushed."""


def _discard_standard_output() -> None:
    """Send what is left of the standard output (and anything written later) to the null device, so that the
    flush at exit does not fail again on text that cannot be written."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):     # not a file (a test's capture)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:200] or type(exc).__name__


def _cmd_reproduce(args) -> int:
    from .reproduce import reproduce

    if args.plots:      # before the simulation and the analysis, as analyze checks --report
        _check_output_directory(args.plots, "--plots")
    _say(reproduce(args.case, samples=args.samples, seed=args.seed, options=_analysis_options(args),
                   plot_dir=args.plots))
    return 0


def _refuse_dash(path, flag: str, expected: str, why: str) -> None:
    """Refuse ``-`` as the output of ``flag`` where it is not the standard output: it would write a file or a
    directory named ``-``, where ``--data -`` and ``--json -`` of ``analyze`` mean the standard streams.

    Raises
    ------
    InputError
        ``"FLAG -: expected EXPECTED (WHY)"``.
    """
    if path == "-":
        raise InputError(f"{flag} -: expected {expected} ({why})")


def _refuse_standard_output(path: str, flag: str, what: str) -> None:
    """:func:`_refuse_dash` of an output file of ``simulate`` or ``export``, whose standard output holds the summary."""
    _refuse_dash(path, flag, f"a file to write {what} to", f"standard output is not supported for {flag}: it holds "
                 f"the summary line")


def _simulate_conflicts(args) -> None:
    """Refuse flags of ``simulate`` that would be ignored or would replace another one: ``--plant``, ``--model``
    and ``--experiment`` with ``--case`` (a case gives its plant, model and excitation), ``--experiment`` with
    ``--dither`` (the experiment gives the dither of every input, instead of ``--dither``).

    Raises
    ------
    InputError
        Naming both flags.
    """
    if args.case:
        for flag, value in (("--plant", args.plant), ("--model", args.model)):
            if value:
                raise InputError(f"{flag} {value} with --case {args.case}: expected --case, or --plant and --model, "
                                 f"not both")
        if args.experiment:
            raise InputError(f"--experiment {args.experiment} with --case {args.case}: expected --experiment with "
                             f"--plant and --model (with --case, give a dither with --dither)")
    if args.experiment and args.dither is not None:
        raise InputError(f"--experiment {args.experiment} with --dither {args.dither!r}: expected one of them "
                         f"(the experiment gives the dither of every input, instead of --dither)")


def _simulable(flag: str, path: str, model) -> None:
    """Refuse, naming ``flag`` and its file, a model whose state space a simulation cannot hold (a dead time or a
    step response of many thousands of samples; :func:`~mpm_monitor.core.discretize.check_state_count`)."""
    from ..core.discretize import check_state_count
    from ..core.errors import ModelFileError

    try:
        check_state_count(model)
    except ModelFileError as exc:
        text = str(exc)
        raise InputError(f"{flag} {path}: {text.removeprefix('simulation: ')}") from None


def _cmd_simulate(args) -> int:
    from ..core.errors import ConfigurationError
    from ..io.csv_log import write_log_csv
    from ..io.model_file import load_model, save_model
    from ..sim.cases import simulation_case
    from ..sim.closed_loop import (ExcitationOptions, at_operating_point, controller_columns, operating_point_conflict,
                                   run_closed_loop)
    from ..sim.excitation import PrbsOptions
    from ..sim.mpc import MpcOptions

    _simulate_conflicts(args)
    dither = 0.0 if args.dither is None else args.dither
    _refuse_standard_output(args.csv, "--csv", "the CSV log")
    _refuse_standard_output(args.write_model, "--write-model", "the controller model")
    for path, what in ((args.csv, "--csv"), (args.write_model, "--write-model")):
        if path:
            _not_an_input(path, what, {"--plant": args.plant, "--model": args.model, "--experiment": args.experiment})
            _check_output_file(path, what)
    _distinct_outputs((("--csv", args.csv), ("--write-model", args.write_model)))
    if args.case:
        case = simulation_case(args.case)
        plant, model, mpc, exc, dist = case.plant, case.model, case.mpc, case.excitation, case.disturbance
        if dither > 0:
            exc = ExcitationOptions(setpoint=exc.setpoint, dither=PrbsOptions(amplitude=dither))
        dv = {} if case.measured_disturbance is None else {"measured_disturbance": case.measured_disturbance}
        log = run_closed_loop(plant, model, args.samples, seed=args.seed, mpc=mpc, excitation=exc, disturbance=dist,
                              **dv)
    else:
        if not (args.plant and args.model):
            raise InputError("simulate: give --case, or both --plant and --model")
        plant, model = load_model(args.plant), load_model(args.model)
        for flag, path, m in (("--plant", args.plant, plant), ("--model", args.model, model)):
            _simulable(flag, path, m)
        if (plant.inputs, plant.outputs, plant.sample_time) != (model.inputs, model.outputs, model.sample_time):
            what = "sample_time" if (plant.inputs, plant.outputs) == (model.inputs, model.outputs) else \
                "inputs and outputs"
            got = (f"{plant.sample_time:g} s vs {model.sample_time:g} s" if what == "sample_time" else
                   f"{list(plant.inputs)} / {list(plant.outputs)} vs {list(model.inputs)} / {list(model.outputs)}")
            raise InputError(f"--plant {args.plant} and --model {args.model}: expected the same {what}, got {got}")
        try:
            controller_columns(plant, model)
        except ConfigurationError as exc:       # named the files neither (an outside check)
            raise InputError(f"--plant {args.plant} and --model {args.model}: {exc}") from None
        conflict = operating_point_conflict(plant, model)
        if conflict:
            raise InputError(f"--plant {args.plant} and --model {args.model}: expected the same operating point (the "
                             f"loop is simulated in deviations from one, and the log written at it), got {conflict}")
        exc = ExcitationOptions(dither=PrbsOptions(amplitude=dither) if dither > 0 else None)
        if args.experiment:
            exc = ExcitationOptions(dither=PrbsOptions(amplitude=1.0, switch_probability=0.5),
                                    dither_amplitudes=_experiment_dither(args.experiment, model))
        log = run_closed_loop(plant, model, args.samples, seed=args.seed, mpc=MpcOptions(), excitation=exc)
    _check_finite_log(log, args)
    log = at_operating_point(log, plant)      # the logged values, as the model file's operating point reads them
    _write_output(args.csv, "--csv", lambda: write_log_csv(args.csv, log))
    if args.write_model:
        _write_output(args.write_model, "--write-model", lambda: save_model(model, args.write_model))
    _say(f"wrote {log.n_samples} samples to {args.csv}; prediction error RMS: "
         + ", ".join(f"{o}={_rms_text(v)}" for o, v in zip(log.outputs, _rms(log.d))))
    return 0


def _check_finite_log(log, args) -> None:
    """Refuse a simulated log that holds a value that is not finite (a loop that overflowed, as a dither of
    1e308 makes it), before its CSV is written: one line naming what drove it (``--dither``, ``--experiment``,
    or the plant and model) and the time of the first such sample.

    Raises
    ------
    InputError
    """
    import numpy as np

    finite = np.ones(log.n_samples, dtype=bool)
    for values in (log.r, log.u, log.y, log.dv, log.d):
        finite &= np.isfinite(values).all(axis=1)
    if finite.all():
        return
    first = int(np.argmin(finite))
    what = (f"the simulated log holds values that are not finite from t = {_text(float(log.t[first]))} s (sample "
            f"{first + 1} of {log.n_samples}): the closed loop overflowed")
    if args.experiment:
        raise InputError(f"--experiment {args.experiment}: {what}: expected smaller dither amplitudes")
    if args.dither:
        raise InputError(f"--dither {args.dither!r}: {what}: expected a smaller dither amplitude")
    source = f"--case {args.case}" if args.case else f"--plant {args.plant} with --model {args.model}"
    raise InputError(f"{source}: {what}: expected a plant that the model's controller keeps bounded")


def _rms(d):
    """The root mean square of every column of ``d``, without overflowing on values above 1e154."""
    import numpy as np

    with np.errstate(over="ignore"):        # the squares of values above 1e154 overflow: scaled below
        rms = np.sqrt(np.mean(d ** 2, axis=0))
    if np.all(np.isfinite(rms)):
        return rms
    scale = np.max(np.abs(d), axis=0)
    scale[scale == 0] = 1.0
    return scale * np.sqrt(np.mean((d / scale) ** 2, axis=0))


def _rms_text(value: float) -> str:
    """A prediction error RMS as ``simulate`` prints it: 4 decimals, or 5 significant digits when that is long."""
    return f"{value:.4f}" if value < 1e9 else f"{value:.4e}"


def _experiment_dither(path: str, model) -> tuple:
    """The dither amplitude of every input (0 where none) of the ``experiment`` in an analyze --json report."""
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the report: {str(exc).splitlines()[0] if str(exc) else exc!r}") from None
    except RecursionError:
        raise InputError(f"{path}: cannot read the report: arrays or objects nested too deeply") from None
    exp = doc.get("experiment") if isinstance(doc, dict) else None
    if not isinstance(exp, dict) or not isinstance(exp.get("dither"), dict):
        raise InputError(f"{path}: key 'experiment': expected an object with a 'dither' (this report recommends "
                         f"no experiment)")
    dither = exp["dither"]
    unknown = [k for k in dither if k not in model.inputs]
    if unknown:
        raise InputError(f"{path}: key 'experiment.dither': unknown input(s) {', '.join(unknown)}; the model's "
                         f"inputs are {', '.join(model.inputs)}")
    from ..core.logged_data import MAX_ANALYSIS_SCALE

    bad = [k for k, v in dither.items() if not _finite_amplitude(v)]
    if bad:
        got = repr(dither[bad[0]])
        got = got if len(got) <= 40 else got[:37] + "..."
        raise InputError(f"{path}: key 'experiment.dither': expected finite amplitudes >= 0, got {bad[0]}={got}")
    large = [k for k, v in dither.items() if float(v) > MAX_ANALYSIS_SCALE]
    if large:       # a log dithered beyond it was written, and every reader refuses it
        raise InputError(f"{path}: key 'experiment.dither': expected amplitudes of at most {MAX_ANALYSIS_SCALE:g} "
                         f"(input units: a log dithered beyond it cannot be analysed), got {large[0]}="
                         f"{float(dither[large[0]]):g}")
    return tuple(float(dither.get(name, 0.0)) for name in model.inputs)


def _finite_amplitude(v) -> bool:
    """Whether a report's dither amplitude is a number (not a boolean), finite as a float, and at least 0."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        x = float(v)
    except OverflowError:              # an integer of hundreds of digits
        return False
    return math.isfinite(x) and x >= 0


def _cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(case=args.case, samples=args.samples, bag=args.bag, seed=args.seed, quiet=args.quiet,
                    out=_CheckedStandardOutput)


def _resolved(path) -> Path:
    """``Path(path).resolve()``, or the absolute path as given where that cannot be resolved (a symbolic link that
    points to itself: ``resolve`` raised a RuntimeError traceback before the input was looked at; the reader then
    names the path)."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError):
        return Path(os.path.abspath(path))


def _distinct_outputs(outputs) -> None:
    """Refuse two of a command's outputs ``(flag, path)`` (in the order written; a path None, empty or "-" is none)
    on one path: the second would overwrite the first.

    Raises
    ------
    InputError
    """
    given = [(flag, path) for flag, path in outputs if path and path != "-"]
    for k, (flag, path) in enumerate(given):
        for other, before in given[:k]:
            if _resolved(path) == _resolved(before):
                raise InputError(f"{flag} {path}: the same path as {other}: expected another path (the second "
                                 f"would overwrite the first)")


def _report_apart(args) -> None:
    """Refuse a ``--report`` directory that would overwrite an input or another output: one of the files it writes
    (or removes, stale: :data:`~mpm_monitor.io.report.REPORT_FILES`) is the ``--model`` or ``--data`` input or the
    ``--json`` or ``--repair-out`` output, or the directory lies in the ``--bag`` input.  Those replaced the input
    or the JSON report with the HTML or a figure, without a word.

    Raises
    ------
    InputError
    """
    from ..io.report import REPORT_FILES

    _not_an_input(args.report, "--report", {"--bag": args.bag})
    others = {"--model": args.model, "--data": args.data, "--json": args.json_out, "--repair-out": args.repair_out}
    for name in REPORT_FILES:
        target = _resolved(Path(args.report) / name)
        for flag, given in others.items():
            if given and given != "-" and _resolved(given) == target:
                role = "input" if flag in ("--model", "--data") else "output"
                raise InputError(f"--report {args.report}: writes {name} there, which is the {flag} {role} {given}: "
                                 f"expected a report directory apart from the inputs and the other outputs")


def _not_an_input(path: str, flag: str, inputs: dict) -> None:
    """Refuse an output ``path`` that is one of the command's input files or lies in its input directory (``inputs``:
    flag -> path), which writing it would destroy (``export --csv BAG/bag_0.mcap``, ``--json`` onto the log).

    Raises
    ------
    InputError
    """
    out = _resolved(path)
    for other, given in inputs.items():
        if not given:
            continue
        src = _resolved(given)
        if out == src or (src.is_dir() and src in out.parents):
            where = "is" if out == src else "lies in"
            raise InputError(f"{flag} {path}: {where} the {other} input {given}: expected an output path apart "
                             f"from the inputs")


def _cmd_export(args) -> int:
    from ..io.bags import export_csv

    _refuse_standard_output(args.csv, "--csv", "the CSV log")
    _not_an_input(args.csv, "--csv", {"--bag": args.bag, "--model": args.model})
    _check_output_file(args.csv, "--csv")          # before the bag is read, as analyze does
    n = export_csv(args.bag, args.csv, model_path=args.model, topics=_topics(args),
                   warn=lambda note: print(f"warning: {note}", file=sys.stderr), bad_values=args.bad_values,
                   hold_setpoint=args.hold_setpoint)
    _say(f"wrote {n} samples to {args.csv}")
    return 0


COMMANDS = {"analyze": _cmd_analyze, "reproduce": _cmd_reproduce, "simulate": _cmd_simulate, "demo": _cmd_demo,
            "export": _cmd_export, "recover": _cmd_recover}


#: Exit code when the standard output's reader closed it before the output was written (128 + SIGPIPE).
BROKEN_PIPE = 141


def _named_as_flag(parser: argparse.ArgumentParser, command: str, message: str) -> str:
    """``message`` with an option named as the library and the nodes name it (``parameter max_delay: ...``,
    ``candidates: ...``) named as the command's flag (``--max-delay: ...``), when the command has a flag that sets it."""
    head, sep, rest = message.partition(": ")
    name = head[len("parameter "):] if head.startswith("parameter ") else head
    if not sep or not name or not name.isidentifier():
        return message
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            for a in action.choices[command]._actions:
                if a.dest == name and a.nargs != 0 and a.option_strings:
                    return f"{a.option_strings[-1]}: {rest}"
    return message


def main(argv=None) -> int:
    """Entry point; returns the exit code (0 ran, 2 bad input or a standard output that cannot be written, 130
    interrupted, :data:`BROKEN_PIPE` the output's reader went away)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    try:
        # numpy's floating-point warnings (an overflow on values or parameters too large for the analysis) are
        # not printed: the analysis checks the scale itself and says what is wrong in one line.
        import numpy as np

        with np.errstate(all="ignore"):
            return COMMANDS[args.command](args)
    except InputError as exc:
        print(f"error: {_named_as_flag(parser, args.command, str(exc))}", file=sys.stderr)
        return 2
    except MemoryError:
        # A log too long for this machine's memory: one line, as for bad input (no traceback of numpy's
        # allocation), and the exit status of a failure that is not the input's fault.
        print(f"error: {args.command}: out of memory (a log of millions of samples? analyse it in parts, or on a "
              f"machine with more memory)", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except _StandardOutputError as exc:
        # ``> /dev/full``, an I/O error: what was not written is lost; the files written are complete.
        _discard_standard_output()
        print(f"error: standard output: cannot write: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of the output went away (``| head``): what is left of the output goes nowhere, quietly,
        # with the exit status of a command that SIGPIPE ended (the files written are complete).
        _discard_standard_output()
        return BROKEN_PIPE


def main_analyze() -> int:
    """Console script ``mpm_analyze``: same as ``python -m mpm_monitor analyze``."""
    return main(["analyze"] + sys.argv[1:])

"""The ``slam`` command: a thin layer over the library.

    slam run DATA [--mode frame2frame|frame2model] [--config FILE] [--out DIR] [--frames A:B:S | N]
                  [--weights learned|constant] [--residuals 2d3d|2d|3d] [--rerun FILE.rrd | --spawn]
                  [--export-map] [--mesh] [--set key=value ...]
    slam compare DATA [--out DIR]
    slam eval GT.txt EST.txt
    slam synth OUT --scenario S [--frames N] [--size WxH] [--seed S] [--raw]
    slam train --config configs/train.yaml [--out DIR]
    slam inspect DATA [--calibration FILE] [--out DIR]
    slam evaluate ROOT [--protocol folder|stereomis|scared] [--modes ...] [--sweep KEY=V1,V2 ...]
                  [--out DIR] [--address ray://HOST:PORT | auto] [--workers N] [--cpus-per-task C]
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from slam.errors import SlamError
from slam.app.interrupts import exit_code, signal_of, terminate_as_interrupt
from slam.app.progress import on_terminal


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line naming the problem (no usage dump)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _add_run_options(p: argparse.ArgumentParser, out_default: str) -> None:
    p.add_argument("data", help="sequence folder (docs/inputs.md: StereoMIS, SCARED, frame folders, ...) or a stereo video file")
    p.add_argument("--calibration", metavar="FILE", help="calibration file to use (.ini, .yaml, .json; docs/inputs.md)")
    p.add_argument("--stereo-layout", choices=["top-bottom", "side-by-side"],
                   help="how a stereo video holds its views (default: from the calibration, then the aspect ratio)")
    p.add_argument("--fps", type=float, help="the frames' rate when they carry no timestamps (data.fps)")
    p.add_argument("--config", help="YAML config (defaults: configs/default.yaml values built in)")
    p.add_argument("--out", help=f"output folder (default {out_default}); one holding an earlier run is refused "
                                 "without --overwrite")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier run in --out (its files are removed first)")
    p.add_argument("--frames", help="frame selection: N (first N), A:B:S, or A:B:S segments joined by commas")
    p.add_argument("--weights", choices=["learned", "constant"], help="learned weight maps or constant weights")
    p.add_argument("--residuals", choices=["2d3d", "2d", "3d"], help="residuals used (ablation)")
    p.add_argument("--rerun", metavar="FILE.rrd", help="save a rerun recording")
    p.add_argument("--spawn", action="store_true", help="open the rerun viewer")
    p.add_argument("--export-map", action="store_true", help="write map.ply in frame2frame too")
    p.add_argument("--mesh", action="store_true", help="also write a surface mesh of the map")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value (repeatable)")
    _add_quiet(p)


def _add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines (results and errors stay)")


def _add_batch_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("where the tasks run (docs/evaluation.md)")
    g.add_argument("--address", metavar="ADDR",
                   help="a Ray cluster: auto (the one this machine belongs to), HOST:PORT or ray://HOST:PORT; "
                        "default: this machine")
    g.add_argument("--executor", choices=["auto", "ray", "local"], default="auto",
                   help="auto: Ray when it is installed (pip install 'endoslam[cluster]'), else local worker "
                        "processes (default)")
    g.add_argument("--workers", type=int, default=0, help="tasks at once on this machine (default: cores / --cpus-per-task)")
    g.add_argument("--cpus-per-task", type=int, default=1, metavar="C",
                   help="CPUs per task (Ray's num_cpus; a run's threads when the config leaves them at 0; default 1)")
    g.add_argument("--timeout", type=float, metavar="SECONDS", help="stop a task that runs longer (default: no limit)")
    g.add_argument("--force", action="store_true", help="run every task, also those whose results are there")
    _add_quiet(p)


def _batch_options(args) -> "BatchOptions":  # noqa: F821
    from slam.batch.runner import BatchOptions

    return BatchOptions(executor=args.executor, address=args.address, workers=args.workers,
                        cpus_per_task=args.cpus_per_task, timeout_s=args.timeout, force=args.force,
                        progress=not args.quiet and on_terminal())


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="slam",
        description="Robust stereo-endoscopy SLAM: dense VO with learned 2D/3D residual weights "
                    "(Hayoz et al. 2023) and a surfel map (frame2model).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=OneLineParser)

    run = sub.add_parser("run", help="track a sequence and write trajectory, metrics, plot and map",
                         description="Track a stereo sequence. Writes trajectory.txt (TUM), metrics.json, "
                                     "trajectory.png, config.yaml, map.ply (frame2model or --export-map).")
    _add_run_options(run, "runs/<sequence>_<mode>")
    run.add_argument("--mode", choices=["frame2frame", "frame2model"], help="tracking mode (default frame2frame)")

    cmp_ = sub.add_parser("compare", help="run frame2frame and frame2model on one sequence; table + plot",
                          description="Run both tracking modes on a sequence; print and write a table and one plot.")
    _add_run_options(cmp_, "runs/<sequence>_compare, one folder per mode in it")

    ev = sub.add_parser("eval", help="ATE-RMSE and RPE of a trajectory against ground truth",
                        description="ATE-RMSE after SE(3) alignment (first-pose alignment on static sequences), "
                                    "RPE-trans and RPE-rot between consecutive frames. TUM files in metres.")
    ev.add_argument("gt", help="ground-truth TUM file")
    ev.add_argument("est", help="estimated TUM file")
    ev.add_argument("--plot", help="also write a trajectory plot (PNG)")
    ev.add_argument("--json", help="also write the metrics as JSON")
    ev.add_argument("--map", metavar="MAP.ply", help="the run's map (with --points): its error against a reference's points")
    ev.add_argument("--points", metavar="REF.ply", help="a reference reconstruction's points (PLY, metres, the ground "
                                                        "truth's world frame), with --map")
    _add_quiet(ev)

    sy = sub.add_parser("synth", help="generate synthetic stereo-endoscopy sequences with ground truth",
                        description="Render a synthetic stereo-endoscopy sequence (StereoMIS layout, or StereoMIS raw "
                                    "with --raw). With several scenarios or seeds, one sequence per pair in "
                                    "OUT/SCENARIO_sSEED, rendered in parallel (Ray or local worker processes); "
                                    "sequences already there with the same parameters are kept.")
    sy.add_argument("out", help="output folder (with several scenarios or seeds: the folder of the sequences)")
    sy.add_argument("--scenario", required=True, nargs="+", choices=["rigid", "breathing", "scanning", "deforming", "loop"])
    sy.add_argument("--frames", type=int, default=150, help="frames to render (default 150)")
    sy.add_argument("--size", default="640x512", help="WxH (default 640x512)")
    sy.add_argument("--seed", nargs="+", default=["0"], help="seeds: N or A-B (inclusive); default 0")
    sy.add_argument("--raw", action="store_true", help="unrectified pair with lens distortion as one mp4 (StereoMIS raw layout)")
    sy.add_argument("--codec", choices=["mp4v", "ffv1"], default="mp4v",
                    help="the raw video's codec: mp4v (lossy .mp4, default) or ffv1 (lossless .avi)")
    sy.add_argument("--breathing-follows-tissue", type=float, default=0.0, metavar="C",
                    help="correlation 0-1 of the breathing amplitude with the tissue's look (red parenchyma "
                         "breathes most); default 0: amplitude independent of the image")
    sy.add_argument("--camera-speed", type=float, default=1.0, metavar="S",
                    help="scale of the rigid and scanning cameras' motion per frame (default 1: 0.3-0.9 mm; "
                         "0.1: a camera creeping below tracking's still threshold)")
    sy.add_argument("--appearance", metavar="SPEC",
                    help="how the tissue looks: 'random' (drawn from the seed: texture, highlights, smoke, exposure, "
                         "vignetting, colour) or KEY=VALUE,... with keys texture (1 rich .. 0 nearly textureless), "
                         "highlights (0 .. 1: a fifth of the view), haze (smoke 0 .. 1), exposure_jitter, vignetting, "
                         "tint; default: the generator's own look")
    _add_batch_options(sy)

    ev2 = sub.add_parser("evaluate", help="many sequences x modes (x swept config values) as parallel tasks; one table",
                         description="Run every sequence of ROOT in every mode (and every swept config value) as one "
                                     "task each, on Ray or local worker processes; gather the runs into the paper's "
                                     "tables (evaluation.md, evaluation.csv, evaluation.png, summary.json). Tasks "
                                     "whose results are there already are not run again.")
    ev2.add_argument("root", help="the folder of sequences (folder), the StereoMIS root or the SCARED root")
    ev2.add_argument("--protocol", choices=["folder", "stereomis", "scared"], default="folder",
                     help="folder: every sequence sub-folder (default); stereomis: the paper's Tables 1-2 from --csv; "
                          "scared: the paper's Table 3 and the map's accuracy")
    ev2.add_argument("--modes", nargs="+", choices=["frame2frame", "frame2model"],
                     help="default: both (folder), frame2frame (stereomis), frame2model (scared)")
    ev2.add_argument("--config", help="YAML config (default: the protocol's, configs/stereomis_frame2frame.yaml or "
                                      "configs/scared_frame2model.yaml; built-in defaults for folder)")
    ev2.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value (repeatable)")
    ev2.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2",
                     help="run every value (repeatable: every combination); a row per value in the tables")
    ev2.add_argument("--frames", help="frame selection of every sequence: N (first N) or A:B:S (folder, scared)")
    ev2.add_argument("--out", help="output folder (default runs/evaluate_<ROOT name>)")
    sm = ev2.add_argument_group("stereomis")
    sm.add_argument("--csv", help="protocol CSV (default configs/stereomis_protocol.csv, a template)")
    sm.add_argument("--split", default="test", help="CSV rows of this split (default test)")
    sc = ev2.add_argument_group("scared")
    sc.add_argument("--datasets", nargs="+", type=int, default=[1, 8, 9], help="dataset numbers (default 1 8 9)")
    sc.add_argument("--keyframes", nargs="+", metavar="dD_kK", help="only these keyframes, e.g. d1_k2 d9_k3")
    sc.add_argument("--gt-depth", metavar="FILE", default="", help="ground-truth depth file name in each keyframe "
                    "folder (default: left_depth_map.tiff, left_depth.npy or left_depth.png)")
    sc.add_argument("--gt-depth-scale-mm", type=float, default=0.01, help="mm per unit of a uint16 depth PNG")
    sc.add_argument("--no-map", action="store_true", help="no map accuracy (and no map export in frame2frame)")
    _add_batch_options(ev2)

    ins = sub.add_parser("inspect", help="what the readers find in a sequence, and a rectified pair to check",
                         description="Print what the readers found (layout, frames, sizes, calibration, rectification, "
                                     "fps, ground truth, masks), check the stereo matches' vertical disparity and "
                                     "write the rectified first pair with horizontal lines.")
    ins.add_argument("data", help="sequence folder or stereo video file")
    ins.add_argument("--calibration", metavar="FILE", help="calibration file to use")
    ins.add_argument("--stereo-layout", choices=["top-bottom", "side-by-side"])
    ins.add_argument("--fps", type=float)
    ins.add_argument("--config", help="YAML config")
    ins.add_argument("--out", help="folder for rectified_pair.png (default runs/inspect_<name>)")
    ins.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    _add_quiet(ins)

    tr = sub.add_parser("train", help="train the weight networks end to end through the pose optimum (DDN)",
                        description="Train the weight networks on sequences with ground truth (configs/train.yaml).")
    tr.add_argument("--config", required=True, help="training config YAML")
    tr.add_argument("--out", help="output folder for checkpoints")
    tr.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    _add_quiet(tr)
    return parser


def _resolved_config(args) -> "SlamConfig":  # noqa: F821
    from slam.config import load_config

    overrides = list(args.set)
    if getattr(args, "calibration", None):
        overrides.append(f"data.calibration={Path(args.calibration).expanduser().resolve()}")
    if getattr(args, "stereo_layout", None):
        overrides.append(f"data.stereo_layout={args.stereo_layout}")
    if getattr(args, "fps", None) is not None:
        overrides.append(f"data.fps={args.fps}")
    if getattr(args, "mode", None):
        overrides.append(f"tracking.mode={args.mode}")
    if getattr(args, "weights", None):
        overrides.append(f"weights.mode={args.weights}")
    if getattr(args, "residuals", None):
        overrides.append(f"weights.residuals={args.residuals}")
    if getattr(args, "rerun", None):
        overrides.append(f"logging.rerun={args.rerun}")
    if getattr(args, "export_map", None):
        overrides.append("logging.export_map=true")
    if getattr(args, "mesh", None):
        overrides.append("logging.mesh=true")
    return load_config(args.config, overrides)


def cmd_run(args) -> int:
    from slam.app.runner import run_from_config

    from slam.app.runner import exit_status

    config = _resolved_config(args)
    result = run_from_config(args.data, config, args.out, args.frames, overwrite=args.overwrite,
                             progress=not args.quiet, spawn=args.spawn)
    return exit_status(result)


def cmd_compare(args) -> int:
    from slam.app.compare import compare

    config = _resolved_config(args)
    return compare(args.data, config, args.out, args.frames, overwrite=args.overwrite, progress=not args.quiet,
                   spawn=args.spawn)


def cmd_eval(args) -> int:
    from slam.app.eval_command import main_eval

    return main_eval(args.gt, args.est, plot_path=args.plot, json_path=args.json, map_path=args.map,
                     points_path=args.points)


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SlamError(f"--size {text}: expected WxH, e.g. 640x512") from None
    if w < 16 or h < 16:
        raise SlamError(f"--size {text}: too small")
    return w, h


def cmd_synth(args) -> int:
    from slam.batch.synth import parse_seeds, synthesize
    from slam.batch.tasks import SynthTask
    from slam.synth import generate
    from slam.synth.appearance import appearance_tag, parse_appearance

    seeds = parse_seeds(args.seed)
    size = parse_size(args.size)
    scenarios = list(dict.fromkeys(args.scenario))
    if len(scenarios) == 1 and len(seeds) == 1:
        scenario, seed = scenarios[0], seeds[0]
        out = generate(args.out, scenario, frames=args.frames, size=size, seed=seed, raw=args.raw,
                       progress=not args.quiet,
                       codec=args.codec, breathing_follows_tissue=args.breathing_follows_tissue,
                       camera_speed=args.camera_speed, appearance=parse_appearance(args.appearance, seed))
        print(f"wrote {args.frames} frames ({scenario}, seed {seed}) to {out}")
        return 0
    parse_appearance(args.appearance, 0)   # a bad spec fails here, before anything runs
    root = Path(args.out).expanduser().resolve()      # workers may start in another folder
    tasks = [SynthTask(out_dir=str(root / f"{scenario}_s{seed}{appearance_tag(args.appearance)}"), scenario=scenario,
                       seed=seed, frames=args.frames, size=size, raw=args.raw, codec=args.codec,
                       appearance=args.appearance or "", breathing_follows_tissue=args.breathing_follows_tissue,
                       camera_speed=args.camera_speed)
             for scenario in scenarios for seed in seeds]
    outcomes, interrupted = synthesize(tasks, _batch_options(args))
    failed = sum(o.get("status") != "ok" for o in outcomes.values())
    print(f"{len(tasks)} sequences in {root}: {len(outcomes) - failed} rendered, {len(tasks) - len(outcomes)} there "
          f"already{'' if not interrupted else ' or not started (interrupted)'}, {failed} failed")
    return 130 if interrupted else (1 if failed else 0)


def cmd_evaluate(args) -> int:
    from slam.batch.evaluate import EvaluateRequest, evaluate

    req = EvaluateRequest(root=Path(args.root), protocol=args.protocol, modes=args.modes or [], config=args.config,
                          overrides=list(args.set), sweeps=list(args.sweep), frames=args.frames,
                          out=Path(args.out) if args.out else None, csv=Path(args.csv) if args.csv else None,
                          split=args.split, datasets=args.datasets,
                          keyframes=[k.lower() for k in args.keyframes] if args.keyframes else None,
                          gt_depth=args.gt_depth, gt_depth_scale_mm=args.gt_depth_scale_mm, no_map=args.no_map,
                          batch=_batch_options(args))
    return evaluate(req)


def cmd_inspect(args) -> int:
    from slam.app.inspect import inspect

    inspect(args.data, _resolved_config(args), Path(args.out) if args.out else None)
    return 0


def cmd_train(args) -> int:
    from slam.training.trainer import train_from_config

    train_from_config(args.config, args.out, args.set, progress=not args.quiet)
    return 0


def configure_logging() -> None:
    """Warnings and errors of the project on standard error, one line each; ``slam run`` adds
    its ``run.log`` (info and above) for the run."""
    root = logging.getLogger()
    for old in [h for h in root.handlers if getattr(h, "slam_console", False)]:    # main() called again
        root.removeHandler(old)
    handler = logging.StreamHandler()
    handler.slam_console = True
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    root.setLevel(logging.WARNING)


def main(argv: list[str] | None = None) -> int:
    """Exit codes (README, Outputs): 0 done; 1 ``evaluate``/``synth`` with failed tasks; 2 a
    usage, input or output error (one line); 3 a run that is not a result; 128 + the signal
    when stopped by Ctrl-C (130) or SIGTERM (143), with what was finished written."""
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging()
    handlers = {"run": cmd_run, "compare": cmd_compare, "eval": cmd_eval, "synth": cmd_synth, "train": cmd_train,
                "inspect": cmd_inspect, "evaluate": cmd_evaluate}
    try:
        with terminate_as_interrupt():
            return handlers[args.command](args)
    except KeyboardInterrupt as err:
        print(f"slam {args.command}: interrupted", file=sys.stderr)
        return exit_code(signal_of(err))
    except SlamError as err:
        return _error(args.command, str(err))
    except (ValueError, FileNotFoundError) as err:
        # configuration mistakes surfacing from the library layers (e.g. a missing checkpoint)
        return _error(args.command, str(err))
    except OSError as err:
        # an output that cannot be written (a file in the way, no permission, a full disk); what
        # a run had finished is on disk already (trajectory rows are written as they come)
        where = f"{err.filename}: " if err.filename else ""
        return _error(args.command, f"{where}{err.strerror or err}")


def _error(command: str, message: str) -> int:
    """The one error format of every command: ``slam COMMAND: error: MESSAGE`` on one line, exit 2."""
    print(f"slam {command}: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

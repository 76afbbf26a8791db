"""Kill a training run with SIGKILL at random moments, resume it each time, and check that
it always resumes and ends where an uninterrupted run ends.

    python scripts/resume_soak.py --kills 20 --seed 0 --out out/resume_soak

A run of the builtin reach task checkpoints after every iteration, so most of its wall
time is spent writing checkpoints and a random moment mostly falls inside a write. Each
cycle starts ``scripts/train.py`` (the first fresh, then ``--resume``), waits until the
run has written a checkpoint it did not have, then kills it after a random delay (uniform
in ``[0, --window]`` s). After the last kill the run is resumed to its end, and its policy
and metrics are compared, bit for bit, with an uninterrupted run of the same file.
Writes ``OUT/report.json`` (every kill: when, the newest checkpoint before it, what the
next resume said) and exits 1 if any resume failed or the final run differs.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from mysim_jax.mappo.config import reach_training_text

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "scripts" / "train.py"
TIMING = {"wall_s", "iteration_s"}


def _steps(run: Path) -> list[int]:
    folder = run / "checkpoints"
    return sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) if folder.is_dir() else []


def _rows(path: Path) -> list[dict]:
    with path.open() as f:
        return [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(f)]


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kills", type=int, default=20, help="SIGKILLs (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments (default 0)")
    parser.add_argument("--iterations", type=int, default=400, help="iterations of the run (default 400)")
    parser.add_argument("--window", type=float, default=2.0, help="largest delay after a new checkpoint, s")
    parser.add_argument("--out", required=True, help="output folder (created; must not hold a run)")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        print(f"error: --out {out}: not empty", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    cfg = out / "reach.yaml"
    cfg.write_text(reach_training_text("resume_soak", 32 * 16 * args.iterations, checkpoint_every=1,
                                       keep_checkpoints=2))
    rng = random.Random(args.seed)
    quiet = dict(cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    whole, killed = out / "whole", out / "killed"
    res = subprocess.run([sys.executable, str(TRAIN), str(cfg), "--out", str(whole), "--no-eval", "--no-progress"],
                         **quiet)
    if res.returncode != 0:
        print(res.stderr, file=sys.stderr)
        return 1
    kills, ok = [], True
    for k in range(args.kills):
        cmd = ([str(cfg), "--out", str(killed)] if k == 0 else ["--resume", str(killed)])
        before = _steps(killed)
        proc = subprocess.Popen([sys.executable, str(TRAIN), *cmd, "--no-eval", "--no-progress"], **quiet)
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None and not set(_steps(killed)) - set(before):
            time.sleep(0.005)
        delay = rng.uniform(0.0, args.window)
        time.sleep(delay)
        if proc.poll() is not None:
            stdout, stderr = proc.communicate()
            kills.append({"kill": k, "ended_before_the_kill": True, "exit": proc.returncode, "stderr": stderr[-2000:]})
            ok &= proc.returncode == 0
            break
        newest = max(_steps(killed), default=None)
        os.kill(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        said = [line for line in stdout.splitlines() if line.startswith(("resuming", "skipping", "moved"))]
        kills.append({"kill": k, "delay_s": round(delay, 3), "newest_checkpoint_before": newest, "said": said,
                      "leftovers": sorted(p.name for p in (killed / "checkpoints").iterdir()
                                          if not p.name.isdigit() and not p.name.endswith(".sha256.json"))})
        print(f"kill {k + 1}/{args.kills}: after {delay:.2f} s, newest checkpoint {newest}; "
              f"{' / '.join(said) or 'fresh start'}", flush=True)
    res = subprocess.run([sys.executable, str(TRAIN), "--resume", str(killed), "--no-eval", "--no-progress"], **quiet)
    final_ok = res.returncode == 0
    same_policy = final_ok and ((killed / "policy" / "policy.msgpack").read_bytes()
                                == (whole / "policy" / "policy.msgpack").read_bytes())
    same_rows = final_ok and _rows(killed / "metrics.csv") == _rows(whole / "metrics.csv")
    skipped = sum(any(s.startswith("skipping") for s in k.get("said", [])) for k in kills)
    in_write = sum(any("tmp" in name for name in k.get("leftovers", [])) for k in kills)
    report = {"kills": len(kills), "seed": args.seed, "iterations": args.iterations, "final_resume_exit": res.returncode,
              "final_stderr": res.stderr[-2000:] if not final_ok else "", "same_policy": same_policy,
              "same_metrics": same_rows, "kills_inside_a_checkpoint_write": in_write,
              "resumes_that_skipped_a_damaged_checkpoint": skipped, "each": kills}
    (out / "report.json").write_text(json.dumps(report, indent=2))
    ok &= final_ok and same_policy and same_rows
    print(f"{len(kills)} kills ({in_write} inside a checkpoint write: an unfinished folder left); every resume {'worked' if final_ok else 'did NOT work'}; final policy "
          f"{'equal' if same_policy else 'DIFFERENT'} and metrics {'equal' if same_rows else 'DIFFERENT'} to an "
          f"uninterrupted run (bit for bit); {skipped} resumes skipped a damaged checkpoint; wrote {out}/report.json")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

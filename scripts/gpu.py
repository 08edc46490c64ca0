#!/usr/bin/env python3
"""One launcher for the recorded GPU runs: a run is a recipe, scripts/recipes/NAME.toml, not a shell script.

    python scripts/gpu.py RECIPE [--set NAME=VALUE ...] [--only GLOB] [--dry-run]
    OUT=runs/kinds KINDS=mnm python scripts/gpu.py kinds         # a variable from the environment, as the scripts did

A recipe (every key optional but the stages):

    log = "{WORK}/logs/stages.log"      # the stage log, besides stdout
    dirs = ["{WORK}/logs"]              # folders made before the first wave
    require = { JOBS = "a file of job lines" }   # variables without a default that must be given
    [vars]                              # defaults, in order (one may use those above it); NAME from the environment or
    WORK = "/tmp/x"                     # --set NAME=VALUE wins over its default ({sh = "LINE"}: the line's output);
    results = "{WORK}/results"          # a lower-case name is the recipe's own: the environment does not set it
    [env]                               # exported to every stage
    [templates.NAME]                    # stage keys shared by stages that say template = "NAME" (built in: gen, train)
    [pack]                              # the results tarball, rewritten after every wave that ran a stage:
                                        # tar of `paths` (default ".") under `dir` less `exclude`, into `into`
                                        # (default DIR/results.tar.gz), then the shell line `then`
    [[stage]]
    name = "data {data}"                # the log's name for it (--only matches it)
    cmd = "python -m ..."               # one bash line (bash -o pipefail -c): pipes, loops and redirections allowed
    wave = 2                            # stages of one wave run at once; the next wave waits for them all. Without
                                        # it: a new wave after every stage above. Waves run in increasing number.
    gpu = "{i}"                         # CUDA_VISIBLE_DEVICES = FIRST_GPU + this mod gpus; without it, inherited
    done = "{WORK}/data/R1/summary.json"  # skipped when this path exists (a rerun goes on where the last stopped)
    when = '[ -n "{G_NEW}" ]'           # skipped unless this bash test holds when its wave starts
    for = { kind = "{KINDS}" }          # one stage per item: the list split at ';' where it has one (so "{V};" is
                                        # a ';' list even of one item), else at blanks; a key "name=flags" or
                                        # "name batch flags" splits each item into those fields (the last the rest)
    serial = true                       # the copies one after another (copy i in wave W + i), not all at once
    job = "{gpus} * {PER_GPU}"          # a jax.distributed job of N processes: {proc} each one's index, {job} its flags
    report = "tail -1 {WORK}/x.log"     # a bash line whose output ends the stage's log line
    env = { WARP_CACHE_PATH = "..." }   # exported to this stage
    # any other key is a field of the stage: {key} in its commands

Variables: {NAME} is a variable: the recipe's, the stage's fields and the built-ins gpus (GPUS, else the GPUs
`nvidia-smi -L` lists, else 1; with FIRST_GPU, the launcher's GPUs are FIRST_GPU .. FIRST_GPU + GPUS - 1, so that
several share a host), gpu_ids ("0 1 ..."), cores (CORES, else this process's cores), i (the item's index in
`for`), proc and job, share (cores / the stages of its wave, at least 1) and fraction (0.9 / the most stages of its wave
on one GPU: XLA_PYTHON_CLIENT_MEM_FRACTION). Braces that are not {NAME} (bash's ${x}, awk's {print $1}) stay as they
are. `wave`, `gpu` and `job` are integer expressions (+ - * / %). A failed stage is named and the launcher exits 1
after its wave; a stage that exits 75 ends the run after its wave with status 0 (the rest waits for the next call).
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import re
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

RECIPES = Path(__file__).resolve().parent / "recipes"
STOP = 75  # a stage's exit status that ends the run, not as a failure
RESERVED = {"name", "cmd", "template", "wave", "serial", "gpu", "done", "when", "for", "job", "report", "env"}
VAR = re.compile(r"(?<!\$)\{([A-Za-z_]\w*)\}")

TEMPLATES = {  # the old scripts/gpu_lib.sh helpers gen and train
    "gen": dict(  # EPISODES episodes of 10 pushes into {WORK}/data/{data}
        name="data {data}", flags="",
        cmd="python -m experiments.generate_data --out {WORK}/data/{data} --episodes {EPISODES} --pushes 10 "
            "--worlds {worlds} --seed {seed} --workers {workers} --no-progress {DATA_FLAGS} {flags} "
            "> {WORK}/logs/data_{data}.log 2>&1",
        done="{WORK}/data/{data}/summary.json",
        report="grep -o '\"frames\": [0-9]*' {WORK}/logs/data_{data}.log"),
    "train": dict(  # --recipe shipped on the sets {data} (names under {WORK}/data), STEPS steps, into {WORK}/runs/{run}
        name="train {run}", flags="",
        cmd="python -m experiments.train_dynamics --recipe shipped --data $(printf '{WORK}/data/%s ' {data}) "
            "--out {WORK}/runs/{run} --steps {STEPS} --eval-every 2000 --max-minutes {BOX} --quiet {flags} "
            "> {WORK}/logs/train_{run}.log 2>&1 && touch {WORK}/runs/{run}/done",
        done="{WORK}/runs/{run}/done",
        report="tail -1 {WORK}/runs/{run}/metrics.jsonl"),
}


def fill(text, values: dict) -> str:
    """text with each {NAME} replaced by its value; an unknown NAME is an error."""
    def one(m):
        if m.group(1) not in values:
            raise KeyError(f"{{{m.group(1)}}} is no variable here: {str(text)[:100]}")
        return str(values[m.group(1)])
    return VAR.sub(one, str(text))


def arith(text, values: dict) -> int:
    """An integer expression after filling in its variables: digits, + - * / % and parentheses (/ rounds down)."""
    expr = fill(text, values)
    if not re.fullmatch(r"[\d\s+\-*/%()]+", expr):
        raise ValueError(f"not an integer expression: {expr!r}")
    return int(eval(expr.replace("/", "//")))  # numbers and operators only, checked above


def count_gpus() -> int:
    """GPUS, else the GPUs that `nvidia-smi -L` lists, else 1."""
    if os.environ.get("GPUS"):
        return int(os.environ["GPUS"])
    try:
        listing = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout
    except OSError:
        listing = ""
    return max(1, sum(line.startswith("GPU") for line in listing.splitlines()))


def shell(line: str) -> subprocess.CompletedProcess:
    """One bash line run to its end, its output captured."""
    return subprocess.run(["bash", "-o", "pipefail", "-c", line], capture_output=True, text=True)


def variables(recipe: dict, sets: dict) -> dict:
    """The built-ins, then each variable: --set, else a non-empty environment variable (not for a lower-case name: the
    recipe's own), else its default filled in."""
    gpus = count_gpus()
    cores = int(os.environ.get("CORES") or len(os.sched_getaffinity(0)))
    values = dict(gpus=gpus, gpu_ids=" ".join(map(str, range(gpus))), cores=cores)
    declared = {**dict.fromkeys(recipe.get("require", {}), ""), **recipe.get("vars", {})}
    unknown = set(sets) - set(declared)
    if unknown:
        raise SystemExit(f"--set {', '.join(sorted(unknown))}: not a variable of this recipe")
    for name, default in declared.items():
        if name in sets or (os.environ.get(name) and not name.islower()):
            values[name] = sets.get(name, os.environ.get(name))
        elif isinstance(default, dict):
            values[name] = shell(fill(default["sh"], values)).stdout.strip()
        else:
            values[name] = fill(default, values)
    missing = [f"{n} ({why})" for n, why in recipe.get("require", {}).items() if not values[n]]
    if missing:
        raise SystemExit("give " + "; ".join(missing))
    return values


def items(loops: dict, values: dict) -> list[dict]:
    """The fields of each copy of a `for` stage: the product of its lists, the first key outermost."""
    copies = [{}]
    for key, text in loops.items():
        listed = fill(text, values)
        words = [w.strip() for w in listed.split(";") if w.strip()] if ";" in listed else listed.split()
        names = re.findall(r"\w+", key)  # "name=flags": fields name and flags, split at "=" (blanks: at blanks)
        sep = re.search(r"\w(\W+)\w", key)
        sep = (sep.group(1).strip() or None) if sep else None
        fields = []
        for word in words:
            parts = word.split(sep, len(names) - 1)
            fields.append(dict(zip(names, parts + [""] * (len(names) - len(parts)), strict=True)))
        copies = [{**c, **f} for c in copies for f in fields]
    return copies


def expand(recipe: dict, values: dict) -> list[dict]:
    """Every stage the recipe makes (for items and job processes apart), in wave order, its commands filled in."""
    templates = {**TEMPLATES, **recipe.get("templates", {})}
    first_gpu = int(os.environ.get("FIRST_GPU") or 0)
    stages, last = [], 0
    for n, own in enumerate(recipe.get("stage", [])):
        entry = {**templates[own["template"]], **own} if "template" in own else own
        made = []
        for i, fields in enumerate(items(entry.get("for", {}), values)):
            local = {**values, **fields, "i": i, "share": "{share}", "fraction": "{fraction}"}  # those two: per wave
            for key, text in entry.items():  # the stage's fields (a template's defaults yield to its for fields)
                if key not in RESERVED and (key in own or key not in fields):
                    local[key] = fill(text, local)
            count = arith(entry["job"], local) if "job" in entry else 1
            port = free_port() if "job" in entry else None
            for proc in range(count):
                job = f"--coordinator localhost:{port} --num-processes {count} --process-id {proc}" if port else ""
                v = {**local, "proc": proc, "job": job}
                name = fill(entry.get("name", f"stage {n + 1}"), v) + (f" #{proc}" if port else "")
                gpu = first_gpu + arith(entry["gpu"], v) % values["gpus"] if "gpu" in entry else None
                wave = (arith(entry["wave"], v) if "wave" in entry else last + 1) + (i if entry.get("serial") else 0)
                made.append(dict(name=name, wave=wave, gpu=gpu, entry=entry, vars=v))
        last = max([last] + [s["wave"] for s in made])
        stages += made
    for wave in {s["wave"] for s in stages}:
        share_out([s for s in stages if s["wave"] == wave], values["cores"])
    return sorted(stages, key=lambda s: s["wave"])  # stable: the recipe's order within a wave


def share_out(wave: list[dict], cores: int):
    """Fill in the commands of one wave's stages, with its {share} of the cores and its GPU memory {fraction}."""
    busiest = max(sum(t["gpu"] == s["gpu"] for t in wave) for s in wave)
    shares = {"{share}": str(max(1, cores // len(wave))), "{fraction}": str(round(0.9 / busiest, 3))}
    for s in wave:
        v = {k: str(x) for k, x in s["vars"].items()}
        for placeholder, value in shares.items():  # in the stage's fields too
            v = {k: x.replace(placeholder, value) for k, x in v.items()}
        s.update({k: fill(s["entry"][k], v) if k in s["entry"] else "" for k in ("cmd", "done", "when", "report")})
        s["env"] = {k: fill(x, v) for k, x in s["entry"].get("env", {}).items()}


def free_port() -> int:
    """A TCP port free now, for a job's coordinator."""
    with socket.socket() as s:
        s.bind(("", 0))
        return s.getsockname()[1]


class Log:
    """The stage log: each line with the time, on stdout and (where the recipe names one) in a file."""

    def __init__(self, path: str | None):
        self.path = path
        if path:
            os.makedirs(os.path.dirname(path) or ".", exist_ok=True)

    def __call__(self, line: str):
        line = f"{time.strftime('%H:%M:%S')} {line}"
        print(line, flush=True)
        if self.path:
            with open(self.path, "a") as f:
                print(line, file=f)


def pack(spec: dict, values: dict):
    """The results tarball: `paths` under `dir` less `exclude` (and itself), written atomically, then `then`."""
    root = fill(spec["dir"], values)
    into = fill(spec.get("into", os.path.join(root, "results.tar.gz")), values)
    excludes = spec.get("exclude", [])
    excludes = [excludes] if isinstance(excludes, str) else excludes
    name = os.path.basename(into)
    flags = [f"--exclude={fill(x, values)}" for x in [name, name + ".tmp", *excludes]]
    paths = fill(spec.get("paths", "."), values).split()
    subprocess.run(["tar", "-czf", into + ".tmp", *flags, "-C", root, *paths], stderr=subprocess.DEVNULL)
    if os.path.exists(into + ".tmp"):
        os.replace(into + ".tmp", into)
    if spec.get("then"):
        subprocess.run(["bash", "-c", fill(spec["then"], values)])


def run_wave(stages: list[dict], env: dict, log: Log) -> tuple[list[str], bool, bool]:
    """Start every stage of one wave that is not done, wait for all; the failed ones, whether one stopped the run and
    whether any ran."""
    running = []
    for s in stages:
        if s["done"] and os.path.exists(s["done"]):
            log(f"{s['name']}: skipped, {s['done']} exists")
        elif s["when"] and shell(s["when"]).returncode:
            log(f"{s['name']}: skipped, not {s['when']}")
        else:
            gpu = {} if s["gpu"] is None else {"CUDA_VISIBLE_DEVICES": str(s["gpu"])}
            log(f"{s['name']}: start" + (f" on GPU {s['gpu']}" if gpu else ""))
            proc = subprocess.Popen(["bash", "-o", "pipefail", "-c", s["cmd"]], env={**env, **s["env"], **gpu})
            running.append((s, time.time(), proc))
    failed, stopped, ran = [], False, bool(running)
    while running:
        time.sleep(0.05)
        for s, t0, proc in [r for r in running if r[2].poll() is not None]:
            running.remove((s, t0, proc))
            report = " ".join(shell(s["report"]).stdout.split()) if s["report"] else ""
            status = {0: "done", STOP: "stops the run"}.get(proc.returncode, f"FAILED (exit {proc.returncode})")
            log(f"{s['name']}: {status} in {time.time() - t0:.1f} s" + (f": {report[:2000]}" if report else ""))
            failed += [s["name"]] if proc.returncode not in (0, STOP) else []
            stopped |= proc.returncode == STOP
    return failed, stopped, ran


def dry_run(stages: list[dict], recipe: dict, values: dict):
    """Print every stage: its wave, GPU, name, conditions and command."""
    for s in stages:
        gpu = "inherited" if s["gpu"] is None else s["gpu"]
        notes = f"; done when {s['done']} exists" if s["done"] else ""
        notes += " (it does)" if s["done"] and os.path.exists(s["done"]) else ""
        notes += f"; when {s['when']}" if s["when"] else ""
        print(f"wave {s['wave']}, GPU {gpu}: {s['name']}{notes}")
        print("\n".join("    " + line for line in s["cmd"].strip().splitlines()))
    if "pack" in recipe:
        spec = recipe["pack"]
        print(f"after each wave: pack {fill(spec.get('paths', '.'), values)} of {fill(spec['dir'], values)}")


def main(argv=None) -> int:
    """Read the recipe, then run its waves in order (or print them)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("recipe", help="a name in scripts/recipes/ (or a .toml file)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a variable's value")
    parser.add_argument("--only", metavar="GLOB", help="run only the stages whose name matches")
    parser.add_argument("--dry-run", action="store_true", help="print every stage and run nothing")
    args = parser.parse_args(argv)
    path = Path(args.recipe) if args.recipe.endswith(".toml") else RECIPES / f"{args.recipe}.toml"
    if not path.exists():
        raise SystemExit(f"no recipe {path}; there are: {' '.join(sorted(p.stem for p in RECIPES.glob('*.toml')))}")
    recipe = tomllib.loads(path.read_text())
    values = variables(recipe, dict(s.split("=", 1) for s in args.set))
    stages = [s for s in expand(recipe, values) if not args.only or fnmatch.fnmatch(s["name"], args.only)]
    if args.dry_run:
        dry_run(stages, recipe, values)
        return 0
    for folder in recipe.get("dirs", []):
        os.makedirs(fill(folder, values), exist_ok=True)
    log = Log(fill(recipe["log"], values) if "log" in recipe else None)
    env = {**os.environ, **{k: fill(v, values) for k, v in recipe.get("env", {}).items()}}
    log(f"{path.stem}: {len(stages)} stages, {values['gpus']} GPUs, {values['cores']} cores")
    for wave in sorted({s["wave"] for s in stages}):
        failed, stopped, ran = run_wave([s for s in stages if s["wave"] == wave], env, log)
        if ran and "pack" in recipe:
            pack(recipe["pack"], values)
        if failed:
            log(f"failed: {', '.join(failed)}")
            return 1
        if stopped:
            log("stopped: the rest waits for the next call")
            return 0
    log("done")
    return 0


if __name__ == "__main__":
    sys.exit(main())

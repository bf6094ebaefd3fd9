#!/usr/bin/env python3
"""Mutation testing of the back ends and PnP with mutmut 3 (issue #9 item 6).

Usage (from the repository root; never part of the test suite or CI):

    python3 scripts/mutation.py --limit 25 --markdown mutation-report.md   # all modules: 150
    python3 scripts/mutation.py --only 'fusion.estimate.ekf.*' 'fusion.estimate.factors.*' --limit 60
    python3 scripts/mutation.py --list        # mutants per module, time to run them all
    python3 scripts/mutation.py --report-only --limit 25   # re-print the verdicts of that sample

Measured on the shared 2-core machine (load 8-13) with 2 workers: 150 mutants (--limit 25, all
modules) in 10.6 min, 120 (ekf + graph, --limit 60) in 11.1 min, i.e. 4-20 s of one worker per
mutant; --limit 60 on all modules (360 mutants) takes about 30-40 min.  The first run on a clean
checkout adds about 10 min of mutant generation and 5 min of stats collection.  All ~7,500
mutants would take 15-30 hours (see --list), so runs are seeded samples: --limit N per module,
the same N mutants on every run with the same --seed.

What it does:
1. mutmut copies `fusion/` and `tests/` into ./mutants and writes, for every function of the
   modules in MODULES (or --paths), one mutated copy per mutation behind a trampoline that picks
   the active one from the MUTANT_UNDER_TEST environment variable.  Generation is slow (libcst:
   about 10 minutes for all target modules on a loaded 2-core machine) but cached: a file is
   regenerated only when its source is newer than its mutated copy.
2. mutmut runs the test subset (TEST_FILES that exist) once with trampolines to learn which tests
   call which function, then, for each selected mutant, forks and runs only those tests
   (fastest first, stop at the first failure).  A mutant is killed when a test fails, a timeout
   when it runs past (expected time + timeout_constant) * timeout_multiplier.
3. This script selects the mutants (--only patterns, a seeded sample of at most --limit per
   module), runs them, and prints (and with --markdown writes) a per-module score table and the
   surviving mutants (file, line, function, the mutated line) ready for BENCHMARKS.md.

Score = (killed + timeout + crashed) / (mutants run - skipped): mutmut's definition, plus mutants
whose test process crashed (a segfault in gtsam); "no tests" mutants (functions no selected test
calls) count against the score.  With --limit the score is a sample estimate; the table gives its
95 % Wilson interval.

gtsam: the CustomFactor error closures are defined inside the trampolined factor builders, so
gtsam calls the mutated closure; mutmut's default process isolation (fork from the process that
collected the stats) showed no deadlock in 160 mutants.  A mutant that hands gtsam a None noise
model segfaults: that counts as crashed (detected).

Parallel workers: none of the tests in TEST_FILES starts worker processes (the workers=2 tests
live in test_detect.py and test_parallel.py); if a test file added to the subset does, deselect
those tests with --deselect NODEID, because every mutant forks from a process that has already
run pytest and a nested forkserver pool per mutant is slow.

Results and the cache live in ./mutants (git-ignored).  A file new to the module list (--paths)
is regenerated and the test-to-function map recollected (about 5 minutes); use --only to pick
modules within the default list instead.  Pinned to mutmut 3.8.1's internal API (the
`mutmut run` CLI has no way to set the module list or sample mutants).
"""

from __future__ import annotations

import argparse
import ast
import fnmatch
import json
import math
import os
import random
import shlex
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mutmut.mutation.data import SourceFileMutationData

# One thread per process: mutmut forks --max-children workers and the machine is shared.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM"):
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]

# ----------------------------------------------------------------------------- what to mutate
# Globs relative to the repository root ("*" also matches "/").  fusion/qr/pnp.py is being split
# into the package fusion/qr/pnp/; both spellings are listed so either layout works.
MODULES = [
    "fusion/estimate/*.py",
    "fusion/qr/pnp.py",
    "fusion/qr/pnp/*.py",
]
# The tests that cover MODULES; files that do not exist (yet) are skipped.
TEST_FILES = [
    "tests/test_estimate.py",
    "tests/test_pnp.py",
    "tests/test_ekf.py",
    "tests/test_health.py",
    "tests/test_smoother_trust.py",
    "tests/test_decisions.py",  # the tests written against this script's survivors
]
# Test node ids never run under mutation (none needed today, see the module docstring).
DESELECT: list[str] = []

DEFAULT_SEED = 0
DEFAULT_MAX_CHILDREN = 2  # the machine has 2 cores
WILSON_Z = 1.96  # 95 % interval for a sampled score
TRAMPOLINE_HEAD_CHARS = 20_000  # the trampoline import sits right after the module's own imports
MUTANTS = Path("mutants")

# mutmut exit-code classes (mutmut.stats.status_by_exit_code) grouped for the report.
KILLED, TIMEOUT, CRASHED, SURVIVED, NO_TESTS, SKIPPED, NOT_RUN, OTHER = (
    "killed",
    "timeout",
    "segfault",
    "survived",
    "no tests",
    "skipped",
    "not checked",
    "other",
)


@dataclass
class ModuleResult:
    path: str
    n_total: int  # mutants mutmut made for the module
    statuses: Counter = field(default_factory=Counter)
    durations_s: list[float] = field(default_factory=list)

    @property
    def n_run(self) -> int:
        return sum(v for k, v in self.statuses.items() if k not in (NOT_RUN, SKIPPED))

    @property
    def n_detected(self) -> int:
        return self.statuses[KILLED] + self.statuses[TIMEOUT] + self.statuses[CRASHED]


@dataclass
class Survivor:
    path: str
    line: int
    function: str
    name: str
    removed: list[str]
    added: list[str]


# ----------------------------------------------------------------------------- small helpers


def expand_targets(paths: list[str]) -> list[str]:
    """Folders (anything not ending in .py or *) become 'folder/*.py'; files and globs are kept."""
    out = []
    for p in paths:
        p = p.rstrip("/")
        out.append(p if p.endswith((".py", "*")) else f"{p}/*.py")
    return out


def wilson_interval(k: int, n: int, z: float = WILSON_Z) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion k/n (Wilson 1927)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def status_class(exit_code: int | None) -> str:
    from mutmut.stats import status_by_exit_code

    status = status_by_exit_code[exit_code]
    if status in (KILLED, TIMEOUT, CRASHED, SURVIVED, NO_TESTS, SKIPPED, NOT_RUN):
        return status
    if status == "caught by type check":
        return KILLED
    return OTHER  # suspicious, interrupted


def git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "fusion", "tests"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return out + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


# ----------------------------------------------------------------------------- mutmut driving


def configure(
    targets: list[str],
    tests: list[str],
    deselect: list[str],
    timeout_multiplier: float | None,
    timeout_constant: float | None,
):
    """Load [tool.mutmut] from pyproject.toml and override the per-run fields."""
    from mutmut.configuration import config

    cfg = config()
    cfg.only_mutate = list(targets)
    cfg.pytest_add_cli_args_test_selection = list(tests)
    cfg.pytest_add_cli_args = list(cfg.pytest_add_cli_args) + [a for d in deselect for a in ("--deselect", d)]
    if timeout_multiplier is not None:
        cfg.timeout_multiplier = timeout_multiplier
    if timeout_constant is not None:
        cfg.timeout_constant = timeout_constant
    return cfg


TRAMPOLINE_IMPORT = "from mutmut.mutation.trampoline import"  # the head of every mutated copy


def sync_cache_with_targets(targets: list[str]) -> None:
    """Make mutmut regenerate target files whose copy in ./mutants has no mutants.

    mutmut skips a file whose copy in ./mutants is newer than its source, so a file first copied
    unmutated (it was not in the module list then, e.g. before --paths changed) would never get
    mutants.  Such copies are deleted here, with mutmut's test-to-function map, which only knows
    the functions trampolined when it was collected (recollected on the next run, about 5
    minutes).  Other files keep their generated mutants and verdicts.  A change of the test
    subset or of --deselect is handled by mutmut itself (it resets the verdicts and the map)."""
    stale = []
    for src in sorted(Path("fusion").rglob("*.py")):
        copy, meta = MUTANTS / src, MUTANTS / f"{src}.meta"
        if not fnmatch_any(str(src), targets) or not copy.exists():
            continue
        if not meta.exists():
            stale.append(src)
            continue
        has_mutants = bool(json.loads(meta.read_text()).get("exit_code_by_key"))
        with copy.open() as f:
            head = f.read(TRAMPOLINE_HEAD_CHARS)
        if has_mutants and TRAMPOLINE_IMPORT not in head:
            stale.append(src)
    if stale:
        print(f"regenerating mutants of {', '.join(map(str, stale))} (new in the module list)", flush=True)
        for src in stale:
            for suffix in ("", ".meta", ".spans"):
                (MUTANTS / f"{src}{suffix}").unlink(missing_ok=True)
        (MUTANTS / "mutmut-stats.json").unlink(missing_ok=True)


def fnmatch_any(path: str, patterns: list[str]) -> bool:
    return any(fnmatch.fnmatch(path, p) for p in patterns)


def generate_mutants(max_children: int) -> None:
    """mutmut's generation step (cached by mtime), as in mutmut.__main__._run."""
    from mutmut.__main__ import CatchOutput, create_mutants
    from mutmut.mutation.trampoline import set_mutant_under_test
    from mutmut.utils.file_utils import copy_also_copy_files, copy_src_dir, setup_source_paths

    set_mutant_under_test("mutant_generation")
    start = time.monotonic()
    with CatchOutput(spinner_title="Generating mutants (libcst; cached after the first run)"):
        copy_src_dir()
        copy_also_copy_files()
        setup_source_paths()
        stats = create_mutants(max_children)
    print(
        f"    mutants generated in {time.monotonic() - start:.0f} s ({stats.mutated} files regenerated, "
        f"{stats.unmodified} cached)",
        flush=True,
    )


def mutation_data_by_path() -> dict[str, SourceFileMutationData]:
    from mutmut.mutation.data import SourceFileMutationData
    from mutmut.utils.file_utils import walk_mutatable_files

    out = {}
    for path in sorted(walk_mutatable_files()):
        m = SourceFileMutationData(path=path)
        m.load()
        if m.exit_code_by_key:
            out[str(path)] = m
    return out


def select_mutants(
    data: dict[str, SourceFileMutationData], only: list[str], limit: int | None, seed: int
) -> dict[str, list[str]]:
    """Per module: the mutant names matching any --only pattern, at most `limit` of them
    (a uniform sample with a fixed seed, so a rerun picks the same ones)."""
    selected = {}
    for path, m in data.items():
        names = sorted(m.exit_code_by_key)
        if only:
            names = [n for n in names if any(fnmatch.fnmatchcase(n, p) for p in only)]
        if limit is not None and len(names) > limit:
            names = sorted(random.Random(f"{seed}:{path}").sample(names, limit))
        if names:
            selected[path] = names
    return selected


def run_mutants(names: list[str], max_children: int) -> float:
    """Run the named mutants with mutmut; returns the wall time in seconds."""
    from mutmut.__main__ import _run

    start = time.monotonic()
    try:
        _run(names, max_children)
    except SystemExit as e:  # mutmut exits on a failing clean run etc.
        if e.code not in (0, None):
            raise SystemExit(f"mutmut stopped (exit code {e.code}); see its output above") from None
    return time.monotonic() - start


def print_inventory(data: dict[str, SourceFileMutationData], max_children: int) -> None:
    """Mutants per module and what running all of them would cost: the worst case (every mutant
    survives, so all the tests that call its function run; from mutmut's per-test times) and,
    where mutants have run before, the measured mean wall time per mutant."""
    from mutmut.state import state
    from mutmut.stats import load_stats
    from mutmut.utils.format_utils import mangled_name_from_mutant_name

    have_stats = load_stats()
    tests_by_fn, t_test = state().tests_by_mangled_function_name, state().duration_by_test
    print(
        f"{'mutants':>8} {'worst case':>11} {'measured':>9}  module   (minutes with {max_children} workers)"
    )
    tot_n, tot_worst, tot_meas = 0, 0.0, 0.0
    for path, m in data.items():
        names = list(m.exit_code_by_key)
        worst = sum(
            t_test.get(t, 0.0) for n in names for t in tests_by_fn.get(mangled_name_from_mutant_name(n), ())
        )
        done = list(m.durations_by_key.values())
        meas = len(names) * sum(done) / len(done) if done else float("nan")
        tot_n, tot_worst, tot_meas = tot_n + len(names), tot_worst + worst, tot_meas + (meas if done else 0.0)
        print(f"{len(names):8d} {worst / 60 / max_children:11.0f} {meas / 60 / max_children:9.0f}  {path}")
    print(
        f"{tot_n:8d} {tot_worst / 60 / max_children:11.0f} {tot_meas / 60 / max_children:9.0f}  total"
        + ("" if have_stats else "  (no stats yet: run some mutants first)")
    )


# ----------------------------------------------------------------------------- report


def function_span(source: str, func: str, cls: str | None) -> tuple[int, int]:
    """First and last source line of a top-level function or a method (decorators included)."""
    tree = ast.parse(source)
    body = tree.body
    if cls is not None:
        body = next((n.body for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls), [])
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name == func:
            first = min([node.lineno] + [d.lineno for d in node.decorator_list])
            return first, node.end_lineno or node.lineno
    return 1, len(source.splitlines())


def locate_mutation(
    diff: str, source_lines: list[str], span: tuple[int, int]
) -> tuple[int, list[str], list[str]]:
    """Source line of the first changed line of a mutant diff, and the removed / added lines.

    The diff is of the function alone, so its line numbers are relative; the removed line's
    text is looked up in the function's span, nearest to the relative guess."""
    removed, added, rel, guess_rel = [], [], None, None
    for line in diff.splitlines():
        if line.startswith("@@"):
            rel = int(line.split()[1].split(",")[0].lstrip("-"))
            continue
        if rel is None or line.startswith(("---", "+++")):
            continue
        if line.startswith("-"):
            removed.append(line[1:].strip())
            guess_rel = rel if guess_rel is None else guess_rel
            rel += 1
        elif line.startswith("+"):
            added.append(line[1:].strip())
        else:
            rel += 1
    first, last = span
    guess = first + (guess_rel or 1) - 1
    if removed:
        hits = [
            i
            for i in range(max(1, first - 20), last + 1)
            if i <= len(source_lines) and source_lines[i - 1].strip() == removed[0]
        ]
        if hits:
            guess = min(hits, key=lambda i: abs(i - guess))
    return guess, removed, added


def collect_results(
    selected: dict[str, list[str]], data: dict[str, SourceFileMutationData]
) -> tuple[list[ModuleResult], list[Survivor]]:
    from mutmut.mutation.diff_apply import get_diff_for_mutant
    from mutmut.utils.format_utils import orig_function_and_class_names_from_key

    modules, survivors = [], []
    for path, names in selected.items():
        m = data[path]
        res = ModuleResult(path=path, n_total=len(m.exit_code_by_key))
        source = (ROOT / path).read_text()
        source_lines = source.splitlines()
        for name in names:
            status = status_class(m.exit_code_by_key.get(name))
            res.statuses[status] += 1
            if name in m.durations_by_key and status not in (NOT_RUN, NO_TESTS, SKIPPED):
                res.durations_s.append(float(m.durations_by_key[name]))
            if status != SURVIVED:
                continue
            func, cls = orig_function_and_class_names_from_key(name)
            diff = get_diff_for_mutant(name, path=path)
            line, removed, added = locate_mutation(diff, source_lines, function_span(source, func, cls))
            survivors.append(Survivor(path, line, f"{cls}.{func}" if cls else func, name, removed, added))
        modules.append(res)
    survivors.sort(key=lambda s: (s.path, s.line, s.name))
    return modules, survivors


def _code(text: str) -> str:
    return "`" + text.replace("|", "\\|").replace("`", "'") + "`" if text else "(nothing)"


def markdown_report(
    modules: list[ModuleResult],
    survivors: list[Survivor],
    *,
    command: str,
    tests: list[str],
    wall_s: float | None,
    n_ran: int,
    max_children: int,
    sampled: bool,
) -> str:
    import mutmut

    score_note = (
        "Score = (killed + timeout + crashed) / mutants run.  Crashed: the test process died (a segfault "
        "in gtsam, or killed at the hard CPU limit).  A \"no tests\" mutant (no selected test calls its "
        "function) or an \"other\" one (mutmut: suspicious) counts as not killed."
    )
    if sampled:
        score_note += (
            "  Sampled mutants: the interval is the 95 % Wilson interval of the score over all "
            "the module's mutants."
        )
    lines = [
        f"### Mutation score (mutmut {mutmut.__version__}, commit {git_commit()}, "
        f"{time.strftime('%Y-%m-%d', time.gmtime())})",
        "",
        f"Command: `{command}`.  Tests: {', '.join(f'`{t}`' for t in tests)}.",
        score_note,
        "",
        "| module | mutants run / made | killed | timeout | crashed | survived | no tests | other "
        "| score | 95 % interval | s per mutant |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    tot = ModuleResult(path="**all**", n_total=sum(m.n_total for m in modules))
    for r in modules:
        tot.statuses.update(r.statuses)
        tot.durations_s.extend(r.durations_s)
    for m in modules + [tot]:
        n, k = m.n_run, m.n_detected
        lo, hi = wilson_interval(k, n)
        score = f"{100 * k / n:.0f} %" if n else "-"
        mean = f"{sum(m.durations_s) / len(m.durations_s):.1f}" if m.durations_s else "-"
        name = m.path if m is tot else f"`{m.path}`"
        st = m.statuses
        lines.append(
            f"| {name} | {n} / {m.n_total} | {st[KILLED]} | {st[TIMEOUT]} | {st[CRASHED]} | "
            f"{st[SURVIVED]} | {st[NO_TESTS]} | {st[OTHER]} | {score} | "
            f"{100 * lo:.0f}-{100 * hi:.0f} % | {mean} |"
        )
    not_run = tot.statuses[NOT_RUN]
    lines.append("")
    if wall_s is not None and n_ran:
        lines.append(
            f"This run: {n_ran} mutants in {wall_s / 60:.1f} min with {max_children} worker(s) = "
            f"{60 * n_ran / wall_s:.1f} mutants/min, including mutmut's clean run of the "
            "covering tests (and its stats collection, about 5 min, when the cache was empty); "
            "s per mutant: mean wall time of one mutant's test run."
        )
    if not_run:
        lines.append(f"{not_run} selected mutants have no result yet (not run, or the run was interrupted).")
    lines += ["", f"#### Surviving mutants ({len(survivors)})", ""]
    if survivors:
        lines += ["| file | line | function | original → mutant |", "|---|---:|---|---|"]
        for s in survivors:
            change = "<br>".join([f"− {_code(r)}" for r in s.removed] + [f"+ {_code(a)}" for a in s.added])
            lines.append(f"| `{s.path}` | {s.line} | `{s.function}` | {change} |")
    else:
        lines.append("None.")
    return "\n".join(lines) + "\n"


def run_command(argv: list[str]) -> str:
    """The command that produces these verdicts: argv without --report-only / --markdown OUT."""
    kept, skip = [], False
    for a in argv:
        if skip or a == "--report-only":
            skip = False
            continue
        if a == "--markdown":
            skip = True
            continue
        if not a.startswith("--markdown="):
            kept.append(shlex.quote(a))
    return " ".join(["python3 scripts/mutation.py", *kept])


# ----------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--paths", nargs="+", metavar="PATH", help=f"files, folders or globs to mutate instead of {MODULES}"
    )
    ap.add_argument(
        "--tests",
        nargs="+",
        metavar="FILE",
        help="test files to run instead of the existing ones of TEST_FILES",
    )
    ap.add_argument(
        "--deselect", nargs="+", default=[], metavar="NODEID", help="test node ids not to run under mutation"
    )
    ap.add_argument(
        "--only",
        nargs="+",
        default=[],
        metavar="PATTERN",
        help="mutant-name patterns, e.g. 'fusion.estimate.ekf.*' or '*x_run_ekf__*' "
        "(methods: '*xǁ_EkfǁHELPER*')",
    )
    ap.add_argument(
        "--limit",
        type=int,
        metavar="N",
        help="run at most N mutants per module: a uniform sample with --seed",
    )
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument(
        "--max-children",
        type=int,
        default=DEFAULT_MAX_CHILDREN,
        help="mutants tested in parallel (default %(default)s)",
    )
    ap.add_argument(
        "--timeout-multiplier",
        type=float,
        help="a mutant times out after (expected test time + constant) * this (default: pyproject.toml)",
    )
    ap.add_argument("--timeout-constant", type=float, help="seconds added to the expected test time")
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep verdicts already recorded for the selected mutants (default: rerun them)",
    )
    ap.add_argument("--report-only", action="store_true", help="run nothing; report the recorded verdicts")
    ap.add_argument(
        "--list",
        action="store_true",
        help="only generate mutants; print how many each module has and the time to run them all",
    )
    ap.add_argument("--markdown", type=Path, metavar="OUT.md", help="also write the report here")
    args = ap.parse_args(argv)

    os.chdir(ROOT)
    targets = expand_targets(args.paths or MODULES)
    tests = args.tests or [t for t in TEST_FILES if (ROOT / t).exists()]
    deselect = DESELECT + args.deselect
    command = run_command(argv if argv is not None else sys.argv[1:])

    configure(targets, tests, deselect, args.timeout_multiplier, args.timeout_constant)
    if not args.report_only:
        sync_cache_with_targets(targets)
        generate_mutants(args.max_children)
    data = mutation_data_by_path()
    if not data:
        print(f"no mutants: nothing in {targets} matched (run without --report-only first?)", file=sys.stderr)
        return 1
    if args.list:
        print_inventory(data, args.max_children)
        return 0
    selected = select_mutants(data, args.only, args.limit, args.seed)
    if not selected:
        print(f"no mutant matches --only {args.only}", file=sys.stderr)
        return 1

    wall_s, to_run = None, []
    if not args.report_only:
        to_run = [
            n
            for path, names in selected.items()
            for n in names
            if not (args.resume and data[path].exit_code_by_key.get(n) is not None)
        ]
        print(
            f"running {len(to_run)} mutants of {sum(map(len, selected.values()))} selected "
            f"({', '.join(f'{Path(p).name}: {len(n)}' for p, n in selected.items())})",
            flush=True,
        )
        if to_run:
            wall_s = run_mutants(to_run, args.max_children)
        data = mutation_data_by_path()  # reload the verdicts mutmut wrote

    modules, survivors = collect_results(selected, data)
    report = markdown_report(
        modules,
        survivors,
        command=command,
        tests=tests,
        wall_s=wall_s,
        n_ran=len(to_run),
        max_children=args.max_children,
        sampled=args.limit is not None,
    )
    print()
    print(report)
    if args.markdown:
        args.markdown.write_text(report)
        print(f"wrote {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

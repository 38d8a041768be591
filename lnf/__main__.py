"""``python -m lnf``: lists lnf's entry points; ``python -m lnf train|evaluate ARGS...`` runs one of them, and
``python -m lnf sweep-table DIR`` writes the table of a sweep folder again."""
from __future__ import annotations

import importlib
import sys
from typing import Optional, Sequence

HELP = """\
lnf: Lagrangian neural fields. Entry points (ARGS are Hydra overrides, e.g. +experiment=pendulum; --help lists them):

  python -m lnf.train ARGS       train a model: generate the data if needed, train, evaluate on the test set, draw
  lnf-train ARGS                 Figure 3; writes outputs/<scene>/runs/<date>/ (config, checkpoints/last.ckpt,
  python -m lnf train ARGS       metrics.json, figures, run.json); conf/train.yaml
  python -m lnf.evaluate ARGS    evaluate a checkpoint again (ckpt_path=...) with any integrator, time step, horizon
  lnf-evaluate ARGS              or evaluation grid; writes outputs/evaluate/runs/<date>/; conf/evaluate.yaml
  python -m lnf evaluate ARGS
  python -m lnf.train -m ARGS    a sweep (comma-separated values: model.latent_dim=1,2); each job in
                                 outputs/<scene>/multiruns/<date>/<job>/, and the sweep table of all jobs,
                                 sweep_table.csv and sweep_table.md, in that folder (a Hydra callback writes it)
  python -m lnf sweep-table DIR  write the sweep table of the sweep folder DIR again (after a crash, say)
  python -m lnf                  this list

From Python: model = lnf.load("<run>/checkpoints/last.ckpt"). Documentation: docs/ (mkdocs serve).
"""

COMMANDS = {"train": "lnf.train", "evaluate": "lnf.evaluate"}


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(HELP, end="")
        return 0
    command, rest = args[0], args[1:]
    if command in COMMANDS:
        sys.argv = [f"lnf-{command}", *rest]  # Hydra reads its overrides from sys.argv, as the console script does
        importlib.import_module(COMMANDS[command]).main()
        return 0
    if command == "sweep-table" and len(rest) == 1:
        from lnf.training.sweep_table import write_sweep_table

        written = write_sweep_table(rest[0])
        if written is None:
            print(f"python -m lnf sweep-table: {rest[0]} holds no job of a sweep", file=sys.stderr)
            return 1
        print("\n".join(str(p) for p in written))
        return 0
    print(f"python -m lnf: unknown command {' '.join(args)!r}\n\n{HELP}", end="", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

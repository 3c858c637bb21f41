"""One module per `fcnpose-tf` subcommand.

Each module defines NAME, EXAMPLES, `add_arguments(parser)` and `run(args)`,
and imports nothing heavy at module level (TensorFlow only inside `run`).
"""

COMMAND_MODULES = ("summary", "synth", "data", "train", "evaluate", "predict", "compress", "export", "prune", "sweep",
                   "run", "bench")

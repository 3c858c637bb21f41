"""The paper's experiment: pruning rate x fold, resumable, on one machine or a Ray cluster.

Per fold K the unpruned model is trained on the fold's training frames (or reused); per
(fold, rate) it is pruned, retrained, exported to float16 TFLite and measured (Keras and
TFLite) on the fold's validation frames. The results come out in the paper's layout: the
per-fold table ("5-Folds Desktop"), "Pruning Results", "Requirements", "Pruning and
Quantization" (Markdown and CSV), a PCK-vs-FPS plot, and results.json.

    from fcnpose_tf.sweep import LocalExecutor, SweepConfig, parse_rates, run_sweep
    config = SweepConfig(out="results", data="data/ur5", rates=parse_rates("0.5,0.7"), folds=2,
                         epochs=2, retrain_epochs=1, input_size=64, threads=2)
    outcome = run_sweep(config, LocalExecutor())
    print(outcome.report.tables["pruning"].markdown())

Modules: `rates` (rate specs), `jobs` (config, job identity, the job function), `executors`
(local sequential / process pool / Ray), `report` (tables, plot, results.json from the saved
job records), `driver` (`run_sweep`), `retime` (`retime_sweep`: re-measure timings of finished jobs). Importing this package imports no TensorFlow and no Ray.
"""

from fcnpose_tf.sweep.driver import SweepOutcome, prepare_config, run_sweep
from fcnpose_tf.sweep.executors import Executor, LocalExecutor, RayExecutor
from fcnpose_tf.sweep.jobs import Job, SweepConfig, run_job
from fcnpose_tf.sweep.rates import DEFAULT_RATES_SPEC, parse_rates, rate_label, rate_tag
from fcnpose_tf.sweep.report import Table, write_report
from fcnpose_tf.sweep.retime import RetimeOutcome, retime_sweep

__all__ = ["DEFAULT_RATES_SPEC", "Executor", "Job", "LocalExecutor", "RayExecutor", "RetimeOutcome", "SweepConfig",
           "SweepOutcome", "Table", "parse_rates", "prepare_config", "rate_label", "rate_tag", "retime_sweep",
           "run_job", "run_sweep", "write_report"]

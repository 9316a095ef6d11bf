"""A finished job's policy evaluated on end poses other than those it trained on.

The data-source experiment tests each policy on both the generated test split and the
artist poses; a job's own evaluation covers its training source, and the other is
run here once, with the job's own evaluation settings (seed, falls, length), into
`<job>/eval_on_<source>/` — which later reports read instead of evaluating again.
"""

from __future__ import annotations

import json
from typing import Any

from fallkit.config import validate
from fallkit.eval.evaluate import run_eval
from fallkit.experiments.runs import Job


def evaluation_on(job: Job, source: str) -> dict[str, Any]:
    """The eval.json object of `job`'s policy on end-pose source `source` ("default" or "artist")."""
    if str(job.value("env.poses")) == source and job.value("eval.poses") is None:
        return job.summary  # its own evaluation: the training source's test split
    out = job.dir / f"eval_on_{source}"
    cached = out / "eval.json"
    if cached.is_file():
        return json.loads(cached.read_text())
    out.mkdir(exist_ok=True)
    config = validate(job.config)
    config = config.model_copy(
        update={"checkpoint": str(job.dir), "eval": config.eval.model_copy(update={"poses": source, "split": "test"})}
    )
    return run_eval(config, out)

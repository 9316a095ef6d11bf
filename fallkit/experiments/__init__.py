"""The paper's experiments (Sec. V), each one command: a Hydra multirun plus a report.

    python -m fallkit -m experiment=<name>                # the CPU preset (docs/experiments.md)
    python -m fallkit -m experiment=<name> scale=paper    # the paper's scale
    python -m fallkit.experiments experiments/<name>/<time>   # the report again, on existing runs

The experiment configs (`fallkit/conf/experiment/<name>.yaml`) say what is swept and how
long each job trains; `fallkit.experiments.runs` reads an experiment directory (which jobs
finished, failed or never started) and `fallkit.experiments.report` turns it into the
paper's figure and table. Layered above evaluation: it reads what `mode=train` and
`mode=eval` wrote and evaluates a policy on other end poses where an experiment needs it.
"""

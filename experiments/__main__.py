"""`python -m experiments ...`: the same as `python experiments/run.py ...`."""

from experiments.run import cli

if __name__ == "__main__":
    cli()

"""`python -m experiments ...`: the same as `python experiments/run.py ...`."""

from experiments.run import main

if __name__ == "__main__":
    main()

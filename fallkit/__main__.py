"""`python -m fallkit …`: the Hydra app (see fallkit.app)."""

from fallkit.app import main

if __name__ == "__main__":
    main()

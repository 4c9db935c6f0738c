"""`python -m lanevil_train`: imports cli.main so Hydra's job name is `cli`, not `__main__`."""

from lanevil_train.cli import main

if __name__ == "__main__":
    main()

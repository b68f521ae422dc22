"""``python -m sceneforge``: the command line, as ``sceneforge`` (and what
``torchrun ... -m sceneforge train`` starts in every process)."""

from sceneforge.cli.main import main

if __name__ == "__main__":
    main()

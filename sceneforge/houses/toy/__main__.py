"""``python -m sceneforge.houses.toy --bundle``: regenerate the bundled toy houses."""

import argparse

from .bundle import BUNDLE_SEED, write_bundle


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m sceneforge.houses.toy", description="Regenerate sceneforge's bundled toy houses.")
    parser.add_argument("--bundle", action="store_true", required=True,
                        help=f"write houses toy_{BUNDLE_SEED}_000.. into sceneforge/data/toy_houses")
    parser.parse_args()
    for folder in write_bundle():
        print(folder)


if __name__ == "__main__":
    main()

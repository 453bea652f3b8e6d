"""``gsbench list``: the registered methods and evaluators, the built-in scenes and the suites."""

from __future__ import annotations


def add_parser(subparsers) -> None:
    subparsers.add_parser("list", help="methods, evaluators and built-in scenes").set_defaults(func=run)


def run(args) -> int:
    from gsbench.config.suites import load_suite, suite_names
    from gsbench.data.synthetic.builtin import BUILTIN_SCENES
    from gsbench.registry import EVALUATORS, METHODS

    print("methods:    " + (", ".join(METHODS.names()) or "(none registered yet)"))
    print("evaluators: " + ", ".join(EVALUATORS.names()))
    print("scenes (format, the object's mean share of each image, description):")
    for scene in BUILTIN_SCENES.values():
        print(f"  {scene.name:<24} {scene.format:<4} {scene.share:>5.1%}  {scene.description}")
    print("suites (gsbench sweep FILE --suite NAME):")
    for name in suite_names():
        suite = load_suite(name)
        print(f"  {name:<24} {len(suite.scenes)} scenes × seeds {', '.join(map(str, suite.seeds))}: "
              f"{', '.join(suite.scenes)}")
    return 0

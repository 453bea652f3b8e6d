"""``gsbench config``: the resolved configuration of a run and its run id, as YAML."""

from __future__ import annotations

from gsbench.cli.arguments import GT_HELP


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("config", help="print the resolved config of a run")
    parser.add_argument("--method", required=True)
    parser.add_argument("--scene", default="synthetic/spot")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--config", action="append", help="user YAML file (repeatable)")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help="override, e.g. train.iterations=500")
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--gt", default=None, help=GT_HELP)
    parser.set_defaults(func=run)


def run(args) -> int:
    import yaml

    from gsbench.config.checks import check_run_config
    from gsbench.config.run_config import resolve
    from gsbench.registry import METHODS

    method_cls = METHODS.get(args.method)
    cfg = resolve(
        args.method,
        args.scene,
        preset=args.preset,
        user_files=args.config or (),
        overrides=args.set or (),
        method_config_cls=getattr(method_cls, "Config", None),
        seed=args.seed,
        gt=args.gt,
    )
    check_run_config(cfg)
    print(f"# run id {cfg.run_id}")
    print(yaml.safe_dump(cfg.to_dict(), sort_keys=False), end="")
    return 0

"""The science's subcommands of ``hoi-refine``, one module each: ``inspect``, ``replay``, ``refine``, ``verify``.

Each module has ``register(subparsers)``, named as an entry point in pyproject.toml
(``[project.entry-points."hoi_refine.commands"]``), which is how ``common.cli.main`` finds every command.
Heavy imports (MuJoCo, cma) stay inside the handlers, so ``hoi-refine --help`` stays fast. The service's
commands live in ``service/commands``, the deployment's (``up``, ``worker``, ``ray-head``, ``demo``) in
``worker/runtime/commands``.
"""

"""The deployment's subcommands of ``hoi-refine``, one module each: ``up`` (API + local Ray + workers), ``worker``
(Ray worker actors), ``ray-head`` and ``demo`` (the built-in example end to end).

Found like every command through the ``hoi_refine.commands`` entry points (pyproject.toml). Heavy imports (Ray,
the queue) stay inside the handlers so ``hoi-refine --help`` stays fast.
"""

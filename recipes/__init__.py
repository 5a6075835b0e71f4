"""The training recipes of torchrl_silp: hydra jobs over the library's components.

``sac_silp.py`` trains SAC-SILP+ (the main job; DDPG/TD3 and the paper's baselines are
``method=`` configs of it), ``ddpg_silp.py`` runs it over DDPG, ``bc.py`` and ``prm.py`` are the
behaviour-cloning and PRM baselines, ``transfer.py`` runs a trained policy on the MuJoCo twin,
``sweep.py`` runs a grid of them as Ray tasks. Each is a script (``python recipes/sac_silp.py``)
and a module of this package (``torchrl_silp.recipes.sac_silp.train(cfg)``).

What they share: ``builders`` (the env, networks, buffers, loss and optimisers a run is made of),
``update`` (the gradient step and its compilation), ``checkpointing`` (save, resume, rebuild a
run's networks), ``metrics`` (counters, logged metrics, ``summary.json``), ``start`` (device,
seeds and run directory), ``schema`` with ``config/`` (the typed configs and their values).

The recipes import each other by their installed name, ``torchrl_silp.recipes.<module>`` (pyproject.toml
maps this folder to it), not as ``recipes.<module>`` nor relatively: run as ``python recipes/x.py`` a script
has no package, so a relative import fails, and giving it one by setting ``__package__`` (PEP 366) is
deprecated for removal in Python 3.15; a top-level ``recipes`` package would put a generic name into every
user's site-packages and load each module twice under two names (two hydra ``ConfigStore`` registrations,
two identities of each class). An editor follows these imports into the checkout when the checkout is
installed with ``pip install -e . --config-settings editable_mode=strict``, whose link tree static tools read
(the default editable mode maps the folder through an import hook they cannot).
"""

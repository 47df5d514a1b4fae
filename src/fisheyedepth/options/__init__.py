"""Every option the project takes, in one package: what kind each option is (:mod:`.kinds`), the tables
of the model's, the data's, the trainer's and the runtimes' options (:mod:`.tables`), the model's
defaults from its YAML and the rules on options that contradict each other (:mod:`.defaults`), and the
memory an option would need (:mod:`.memory`).

A value of the wrong kind is not what it says: ``'maybe'`` is true to Python (an ``if automask:``
switched it on), a NaN weight compares false with every bound (``truth_weight=nan`` acted as 0), an
infinite one makes every loss non-finite (each step was skipped, then an untrained network was
scored), and a string met a number deep in the loss as a TypeError. So each is refused where its
group is read, before any work, with one line naming the option as the user typed it:
``model.objective.automask: 'maybe' is not a boolean (true or false)``. The entry points check the
configured groups up front (:func:`fisheyedepth.config.check_config`) with the prefix of their
config (``model.``, ``data.datamodule.``); the classes that read them check again with their own
names (``objective.truth_weight``), for a caller without a config.

The trainer's options (``trainer.*``, :data:`.tables.TRAINER_OPTIONS`) are checked by ``train.py``'s
plan, with the options that contradict each other (:func:`.defaults.check_combinations`) and those whose
memory exceeds the machine's (:func:`.memory.check_memory`: each bound a formula of what the option
allocates, beside its reader: :func:`fisheyedepth.synthetic.spec.check_render_memory`,
:func:`fisheyedepth.models.depth_net.check_network_memory`).

A table names the options whose kind it knows; the others (a file, a camera name, a string's choices
with their own message) are left to their reader. The synthetic renderer's table,
:data:`fisheyedepth.synthetic.GENERATE_OPTIONS`, lives beside the renderer (its effects and traffic
bound are the renderer's; the renderer imports this package, which imports nothing else of the
project)."""

from .defaults import model_defaults, model_options
from .kinds import check_options
from .memory import check_memory

__all__ = ["check_memory", "check_options", "model_defaults", "model_options"]

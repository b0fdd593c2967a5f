"""What runs the environments and the tissue, in two halves and the commands beside them.

* :mod:`agents.learning`: training, evaluation, baselines, the scripted and random policies;
  it works on the environments.
* :mod:`agents.lab`: the compression study, the benchmarks, compression and the hard cases;
  it works on the tissue through ``tissue`` and its lab surface ``tissue.lab``.
* :mod:`agents.cli` (the ``probegym`` command line), :mod:`agents.view` (the viewer's
  launcher), :mod:`agents.env_listing` and :mod:`agents.outputs` serve both.
"""

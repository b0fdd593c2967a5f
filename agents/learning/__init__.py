"""The learning half of agents: training (``train``), evaluation and the held-out baselines
(``evaluation``), the scripted and random policies (``policies``), and the tasks' frames for
the docs (``task_frames``). It works on the environments (``envs``) and never on the tissue's
internals."""

"""The lab half of agents: the compression study (``study``), the benchmarks (``bench``), one
scripted compression (``compress``, ``compress_command``), the hard-case catalogue
(``hard_cases``), the tissue's short demo (``tissue_demo``) and compiling the kernels once
after installing (``first_use``). It works on the tissue through ``tissue`` and ``tissue.lab``,
and on the environments where the study holds the probe with the arm."""

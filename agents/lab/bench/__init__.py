"""``probegym bench``: the benchmarks, each printing a table and writing JSON with a Markdown
copy of its table (:mod:`.report`): :mod:`.tissue` (what each part of a tissue step costs),
:mod:`.contact` (each contact strategy's cost and outcome), :mod:`.peer` (against MuJoCo's
own flex), :mod:`.env` (environment steps per second) and :mod:`.sweep` (each method's force
along a sliding sweep against LM)."""

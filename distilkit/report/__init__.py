"""Reports, the last step of a run: a recipe's comparison table (:mod:`.recipe`), each stage run's own report
with its plots (:mod:`.run`, drawn by :mod:`.plots`), and two runs side by side (:mod:`.compare`)."""

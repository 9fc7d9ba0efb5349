"""The paper's numerical cases regenerated (``twin paper``): the cases on the paper's oscillator and servo-hydraulic
rig with their published figures (:mod:`twin.paper.cases`), and their report (:mod:`twin.paper.report`).  The one
place that names the paper's models: the estimation and the reports it uses name none."""

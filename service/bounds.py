"""The one bound on the magnitude of every number noiselab computes with: a model file's numbers
(:mod:`noiselab.model.schema`), a recording's values (:mod:`noiselab.recordings.series`), a control
from the network and a sample the emulator publishes (:mod:`noiselab.wire`,
:mod:`noiselab.nodes.emulator`), a sample the live analyzer takes (:mod:`noiselab.nodes.analyzer`).

One value for all of them, so that whatever one part accepts the next can use: a control the
emulator accepts drives a plant whose published output the recorder writes and the analysis
reads; a bound larger at the wire than at the loader would make a recording that cannot be
analysed out of a control that was accepted.
"""

MAGNITUDE_MAX = 1e50
"""Largest magnitude of any number, in its own units. The predictions and the analysis square
these numbers (variances), sum the squares over a record and square again (the spread of a
variance estimate is a fourth moment; the likelihood of a fit): (1e50)^4 = 1e200 leaves a factor
1e108 below float64's largest number (1.8e308) for the sums over any record and a plant's gains.
No sensor or plant written in any unit system needs more."""

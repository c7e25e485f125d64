"""Pure functional core of the LQG fuzzy-logic active-suspension controller.

No I/O here: offline design produces a versioned artifact of plain arrays
(:mod:`controller.design`), and the runtime step (:mod:`controller.runtime.bank`) works on
preallocated arrays only.  Units are SI throughout.
"""

__version__ = "0.1.0"

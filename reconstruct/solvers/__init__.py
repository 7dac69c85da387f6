"""The iterative solvers of the reconstruction: ADMM (paper section 4, eq. 20-30), steepest descent, and
the protocols they ask of a data term and a prior (:mod:`.interfaces`)."""

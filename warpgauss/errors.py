"""Errors that reach the user as one line.

Every problem with the user's input or request is raised as :class:`WarpgaussError` with a
message that says what is wrong and what to do; the CLI prints it on one line and exits 2.
"""


class WarpgaussError(ValueError):
    """Bad input or an impossible request (missing file, wrong shape, infeasible budget...)."""

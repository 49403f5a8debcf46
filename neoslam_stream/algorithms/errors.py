"""The one error type for input an algorithm refuses.

An algorithm raises :class:`InvalidInput` when the data it was given cannot be used (wrong shape or
dtype, NaN, indices out of range, a frame too small for the crop...): the caller's data is wrong,
not the code. Hosts count such an input as a bad input and go on. Any other exception an algorithm
raises (a plain ``ValueError`` from numpy, an ``IndexError``...) is a bug, and hosts report it as
one instead of hiding it among the bad inputs.
"""

from __future__ import annotations


class InvalidInput(ValueError):
    """The input cannot be processed; the text says why."""

    #: hosts that may not import this module (the runtime knows no algorithm) recognise invalid
    #: input by this class attribute (``neoslam_stream.runtime.node.is_input_error``)
    invalid_input = True

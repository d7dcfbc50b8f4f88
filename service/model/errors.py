"""Errors of the model layer.

Every problem with a model file is reported as one :class:`ModelError`, whose message is a single
line naming the file, the key and what was expected. The CLI prints it and exits with code 2.
"""


class ModelError(ValueError):
    """A model file (or model argument) is invalid. The message is one line."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))

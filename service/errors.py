"""The one base class of bad input that is not a model file's: a flag, a file, a message.

Exit codes (DESIGN.md): a :class:`BadInput` raised anywhere below a command is printed by the CLI as
one line, ``noiselab: <message>``, and the process exits 2. Modules that are not the CLI raise it
(or a subclass) instead of importing the CLI's own error class, so no node or command module
imports the CLI.
"""


class BadInput(ValueError):
    """Bad input named in one line (a flag, a file, a recording); the CLI exits 2."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))

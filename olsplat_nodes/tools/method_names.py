"""The method names the command line offers (``method.METHODS`` has the methods themselves)
and its default encoder (``encoders.spec.DEFAULT_SPEC``).

Kept apart so that building the parser does not import the method table or the encoders,
which pull in numba (``olsplat --help`` must stay fast); ``tests/test_cli.py`` checks they agree."""

DEFAULT_ENCODER = "olsplat-cnn64"

METHOD_NAMES = (
    "outlangsplat",
    "outlangsplat-paper",
    "outlangsplat-noquality",
    "outlangsplat-noconsistency",
    "topk",
    "drsplat",
    "projection",
    "vala",
)

"""The method names the command line offers (``method.METHODS`` has the methods themselves).

Kept apart so that building the parser does not import the method table, which pulls in
numba (``olsplat --help`` must stay fast); ``tests/test_cli.py`` checks the two agree."""

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

"""Ground-truth vocabulary: what every Gaussian is, and the labels annotations use.

A Gaussian has a ``category`` (what surface it is), an ``instance`` id (which building, tree
or car; -1 for stuff such as road or lawn) and an annotation ``label``: the attribute phrase a
person annotating the photo would use ("red roof buildings" covers roof and walls of a
building whose roof is red). Floaters of a reconstructed map have label -1.
"""

from __future__ import annotations

CATEGORIES = ("bare ground", "road", "lawn", "parking", "pavement", "roof", "wall", "tree", "car", "floater")
CATEGORY = {name: i for i, name in enumerate(CATEGORIES)}

ROOF_COLORS = {  # name -> linear-ish RGB of a clean roof
    "red": (0.58, 0.20, 0.14),
    "blue": (0.20, 0.33, 0.58),
    "white": (0.86, 0.86, 0.83),
    "grey": (0.42, 0.43, 0.45),
}

LABELS = (
    "red roof buildings",
    "blue roof buildings",
    "white roof buildings",
    "grey roof buildings",
    "road",
    "lawn",
    "tree",
    "car",
    "parking lot",
    "bare ground",
    "pavement",
)
LABEL = {name: i for i, name in enumerate(LABELS)}

# the label of stuff categories; buildings take their roof colour's label
STUFF_LABEL = {
    "bare ground": "bare ground",
    "road": "road",
    "lawn": "lawn",
    "parking": "parking lot",
    "pavement": "pavement",
    "tree": "tree",
    "car": "car",
}


def building_label(roof_color: str) -> str:
    return f"{roof_color} roof buildings"


# Evaluation queries: the text a user types, the annotation labels it targets, and whether
# its targets are instances (localisation counts them one by one).
QUERIES = (
    ("red roof buildings", ("red roof buildings",), True),
    ("blue roof buildings", ("blue roof buildings",), True),
    ("white buildings", ("white roof buildings",), True),
    ("grey roof buildings", ("grey roof buildings",), True),
    ("buildings", ("red roof buildings", "blue roof buildings", "white roof buildings", "grey roof buildings"), True),
    ("road", ("road",), False),
    ("lawn", ("lawn",), False),
    ("trees", ("tree",), True),
    ("cars", ("car",), True),
    ("parking lot", ("parking lot",), False),
)

"""The interactive viewer behind `python -m framework.view`: a viser web page showing server-side renders of a
trained avatar (session state and rendering in `session`, camera conversion in `camera`, the page in `app`).

May import framework.animation, lightning/, the registries and viser; never the entry points.
"""

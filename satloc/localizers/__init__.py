"""The localizers.

* :mod:`satloc.localizers.database`: the paper's method: a ground-satellite dictionary built from a database
  drive, candidate poses along its path scored by nearest-neighbour co-occurrence;
* :mod:`satloc.localizers.crossview`: localization with no database, the frame's bird's-eye view against the
  satellite map within a GPS-like prior.

It may import the data model, :mod:`satloc.features` and :mod:`satloc.tracking`.
"""

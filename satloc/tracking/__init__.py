"""Tracking, visual odometry and alignment: what carries a localization from one frame to the next.

* :mod:`satloc.tracking.track`: a belief over candidate poses moved by odometry and fused with each frame's
  posterior;
* :mod:`satloc.tracking.vo`: stereo visual odometry;
* :mod:`satloc.tracking.align`: the bird's-eye view of a frame and its alignment with the satellite map.

It imports only the data model.
"""

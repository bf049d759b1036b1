"""Mesh geometry: loading, validation and repair (``mesh``), triangle and sphere BVHs with
their distance, winding and ray kernels (``bvh``), self-intersections (``selfintersect``)."""

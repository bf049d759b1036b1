"""The MuJoCo layer: MuJoCo's C ABI (``abi``), the declared layout of the records the cfuncs
read (``layout``), the collision cfuncs (``hook``), penalty forces and coupling (``forces``),
the table and registry of attached models (``registry``), ``<custom>`` settings (``config``),
``attach``/``load_model``/``Handle`` (``attach``) and the viewer overlay (``view``)."""

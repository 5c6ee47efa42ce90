"""cli: the ``diskf-mesh`` command line, one module per command.

``main`` builds the parser from every command module (``register``), and
turns an InputError into one ``error:`` line with exit status 2. The mesh's
commands (``up``, ``world``, ``agent``) live with their processes in
``sim/`` and ``agents/``.

May import: every layer of diskf_mesh.
"""

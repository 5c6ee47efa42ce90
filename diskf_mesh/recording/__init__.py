"""Recordings of mesh runs as MCAP files (``up --record``, ``world --record``).

    verdicts   an agent's account, in each report, of what it fused and why not the rest
    schemas    the channels and their JSON Schemas;  scene: ``/scene`` for Foxglove's 3-D panel
    writer     the world's recorder (hooks called by ``sim.world.World``)
    layout     the format's name and the run's trace as attachments, cut and joined again
    reader     reading a recording back, whole or cut short
    replay     the engine on exactly what each agent fused; ``command``: ``replay RUN.mcap``
    summary    ``inspect RUN.mcap``;  figures: ``figures --from RUN.mcap``

May import: core, estimators, data, engine, mesh, studies.
"""

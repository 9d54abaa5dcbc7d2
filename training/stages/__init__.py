"""The pipeline's stages, one module each (``collect``, ``bc``, ``dagger``, ``perception``,
``vision``, ``eval``: ``run(run) -> record``), the helpers they share (``flights``,
``fitting``, ``selection``) and the records they write (:mod:`training.stage_records`)."""

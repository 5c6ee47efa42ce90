# a process of a run started as ``python -m`` (a container's command) runs numpy on one BLAS thread, as the
# command line does: ``diskf_mesh.cli`` sets it before numpy loads (``BLAS_ENV``)
import diskf_mesh.cli  # noqa: F401

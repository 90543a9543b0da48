"""Test configuration: float64 everywhere and strict rank promotion (style.md section 7).

Compilation dominates the suite's time, and many tests compile the very same XLA program
(every ``tune`` or ``run_montecarlo`` call builds fresh jitted closures over identical
plants; eager rollouts trace their scan anew). JAX's compilation cache, pointed at a
temporary folder made for this session (removed at exit, so nothing carries over from one
run to the next), compiles each distinct program once per session: a repeated program is
loaded back, the same executable. The subprocesses the tests start inherit it through the
environment. A cache folder set in the environment beforehand is used as it is.

pytest-xdist's workers (pyproject.toml runs two by default) inherit the controller's folder
and each takes a subfolder of its own: JAX writes a cache entry in place, without a lock, so
two processes must not share one folder.
"""

import atexit
import os
import shutil
import tempfile

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache_dir = tempfile.mkdtemp(prefix="jaxflex-tests-xla-cache-")
    atexit.register(shutil.rmtree, _cache_dir, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache_dir
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
if "PYTEST_XDIST_WORKER" in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.path.join(os.environ["JAX_COMPILATION_CACHE_DIR"], os.environ["PYTEST_XDIST_WORKER"])

import jax  # noqa: E402  (after the environment above, which jax reads at import)
import matplotlib  # noqa: E402

matplotlib.use("Agg")
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
# (again through the config, in case jax was imported before this file)
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
for _name, _type in (("jax_persistent_cache_min_compile_time_secs", float), ("jax_persistent_cache_min_entry_size_bytes", int)):
    if _name.upper() in os.environ:
        jax.config.update(_name, _type(os.environ[_name.upper()]))

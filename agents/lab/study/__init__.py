"""The compression study of Tagliabue et al. (2020), reproduced and extended.

``probegym study`` runs it; :func:`agents.lab.study.runner.run_study` is the Python API. This
package file imports nothing, so worker processes can set their thread counts before the
numerical libraries load (:mod:`agents.lab.study.worker`).
"""

"""What accuracy costs in learning: ``probegym study --transfer`` trains a policy on each
cheap contact model and mesh and evaluates it on the accurate one (and on every other), so
that a user can choose what to train on by measurement (docs/study.md, "Transfer")."""

from agents.learning.transfer.run import TransferOutcome, run_transfer
from agents.learning.transfer.spec import Configuration, TransferError, TransferSpec

__all__ = ["Configuration", "TransferError", "TransferOutcome", "TransferSpec", "run_transfer"]

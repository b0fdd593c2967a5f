"""Gymnasium environments: a MuJoCo robot holding a US probe, coupled to the tissue simulator."""

"""The paper's protocols (installed as ``masking_lab.protocols``)."""

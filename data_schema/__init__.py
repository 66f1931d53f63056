"""JSON Schemas for masking_lab files (installed as ``masking_lab.data_schema``)."""

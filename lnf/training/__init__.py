"""Lightning glue around the plain-torch core: LightningModule, DataModule, callbacks."""

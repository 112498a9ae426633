"""The SRV02 plant-emulator process: physics behind a CAN bus."""

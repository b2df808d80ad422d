"""Registration: volumes, multi-image, second images, automatic placement, drag handles."""

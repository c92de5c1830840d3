"""Every figure: fits, image-fit maps, sensitivity maps."""

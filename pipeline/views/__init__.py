"""What a researcher looks at: the Rerun recording's shared parts and blueprints, the variants'
colours, the printed tables."""

"""The residual loop: residuals, the candidate effect library, selection and the before/after report."""

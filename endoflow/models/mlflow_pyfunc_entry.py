"""The code of endoflow's logged MLflow model ("models from code"): MLflow runs this file to build the model
it loads. See :mod:`endoflow.models.mlflow_model`."""

from mlflow.models import set_model
from mlflow.pyfunc import PythonModel

from endoflow.models.mlflow_model import EndoflowPyfunc


class EndoflowMlflowModel(EndoflowPyfunc, PythonModel):
    """:class:`EndoflowPyfunc` as the ``PythonModel`` MLflow loads."""


set_model(EndoflowMlflowModel())

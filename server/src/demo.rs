//! `fresa serve --demo`: a simulated machine so a newcomer can try everything with curl.

use crate::app::App;

pub const DEMO_MACHINE: &str = "demo";

pub async fn ensure_demo_machine(app: &App) {
    match app.store.machine_by_name(DEMO_MACHINE).await {
        Ok(Some(_)) => {}
        Ok(None) => {
            if app.plugins.get("sim-machine").is_none() {
                tracing::error!("--demo needs the sim-machine plugin, which is not loaded");
                return;
            }
            let config = serde_json::json!({
                "time_scale": 1.0,
                "execution_log": app.settings.data_dir.join("demo-execution.log"),
            });
            match app
                .store
                .insert_machine(DEMO_MACHINE, "sim-machine", &config, 50.0, 5000.0)
                .await
            {
                Ok(id) => tracing::info!(
                    machine = id,
                    "demo machine created (sim-machine, real time)"
                ),
                Err(e) => tracing::error!(error = %e, "could not create the demo machine"),
            }
        }
        Err(e) => tracing::error!(error = %e, "could not look up the demo machine"),
    }
}

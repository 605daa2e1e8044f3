//! The model of a resource's application that the boot file's commands build: its FB
//! instances, their parameters and the connections between their ports, looked up through
//! ordered maps so a hostile file costs time in proportion to its size.

use std::collections::BTreeMap;

/// `(FB instance, port)`; an instance inside a subapplication keeps its dotted path.
pub(super) type PortRef = (String, String);

/// One resource's application as the commands leave it.
#[derive(Debug, Default)]
pub(super) struct Resource {
    pub(super) name: String,
    /// Instance → (creation order, FB type).
    pub(super) fbs: BTreeMap<String, (usize, String)>,
    /// Parameters (`WRITE`): port → value, XML escapes decoded.
    pub(super) params: BTreeMap<PortRef, String>,
    /// Connections by destination: what feeds each input, in creation order.
    pub(super) sources: BTreeMap<PortRef, Vec<PortRef>>,
    /// Connections by source: what each output feeds, in creation order.
    pub(super) destinations: BTreeMap<PortRef, Vec<PortRef>>,
}

impl Resource {
    pub(super) fn fb_type(&self, fb: &str) -> Option<&str> {
        self.fbs.get(fb).map(|(_, t)| t.as_str())
    }

    /// The parameter written to `fb.port`, XML escapes decoded.
    pub(super) fn param(&self, fb: &str, port: &str) -> Option<&str> {
        self.params
            .get(&(fb.to_owned(), port.to_owned()))
            .map(String::as_str)
    }

    pub(super) fn sources_of(&self, fb: &str, port: &str) -> &[PortRef] {
        self.sources
            .get(&(fb.to_owned(), port.to_owned()))
            .map_or(&[], Vec::as_slice)
    }

    pub(super) fn destinations_of(&self, fb: &str, port: &str) -> &[PortRef] {
        self.destinations
            .get(&(fb.to_owned(), port.to_owned()))
            .map_or(&[], Vec::as_slice)
    }

    pub(super) fn connect(&mut self, source: PortRef, destination: PortRef) {
        self.destinations
            .entry(source.clone())
            .or_default()
            .push(destination.clone());
        self.sources.entry(destination).or_default().push(source);
    }

    pub(super) fn disconnect(&mut self, source: &PortRef, destination: &PortRef) {
        if let Some(list) = self.destinations.get_mut(source) {
            list.retain(|d| d != destination);
        }
        if let Some(list) = self.sources.get_mut(destination) {
            list.retain(|s| s != source);
        }
    }

    /// Forgets an FB: its parameters and the connections at its ports (a connection's
    /// other end keeps a dangling entry, which reads as an FB that is not there).
    pub(super) fn delete(&mut self, fb: &str) {
        self.fbs.remove(fb);
        for map in [&mut self.sources, &mut self.destinations] {
            let ports: Vec<PortRef> = map
                .range((fb.to_owned(), String::new())..)
                .take_while(|((f, _), _)| f == fb)
                .map(|(k, _)| k.clone())
                .collect();
            for port in ports {
                map.remove(&port);
            }
        }
        let params: Vec<PortRef> = self
            .params
            .range((fb.to_owned(), String::new())..)
            .take_while(|((f, _), _)| f == fb)
            .map(|(k, _)| k.clone())
            .collect();
        for port in params {
            self.params.remove(&port);
        }
    }
}

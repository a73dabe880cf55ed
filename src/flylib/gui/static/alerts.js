// The page's alert line: what the user must know and may not miss (the server is gone,
// a save failed and why, the edits changed in another tab). Text only, never HTML.

let element = null;

function line() {
  if (!element) {
    element = document.createElement("div");
    element.id = "alert";
    element.setAttribute("role", "alert");
    element.hidden = true;
    document.body.prepend(element);
  }
  return element;
}

export function showAlert(text, kind = "error") {
  const div = line();
  div.textContent = text;
  div.className = kind;
  div.hidden = false;
}

export function clearAlert() {
  if (element) { element.hidden = true; element.textContent = ""; }
}

export function alertText() { return element && !element.hidden ? element.textContent : ""; }
